// The backend interface the command runs (sched/backend.h): the registry names every backend and
// rejects unknown and repeated names; every host backend and the cell simulator, made by name and
// driven through Setup / Build / BeginFrame / EndFrame / Finish, give the serial renderer's
// image over a multi-frame camera path (bit for bit where they keep the fixed-point sums); their
// reports have the host form; one writer writes every backend's statistics as JSON and CSV.
#include "sched/backend.h"

#include <doctest/doctest.h>
#include <nlohmann/json.hpp>

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "scenes/load.h"
#include "sched/mpi_backend.h"
#include "sim/cell_renderer.h"
#include "sim/spe.h"

namespace rs {
namespace {

BackendRegistry All() {
  BackendRegistry r;
  RegisterHostBackends(r);
  sim::RegisterCellBackend(r);
  RegisterMpiBackend(r);
  return r;
}

RenderOptions Options() {
  RenderOptions o;
  o.width = 40;
  o.height = 30;
  o.max_depth = 3;
  return o;
}

// The serial reference's fixed-point sums of frames 0..frames-1 of cornell's camera path.
std::vector<std::vector<int64_t>> SerialSums(const Scene& scene, const Accel& accel, int frames) {
  std::vector<std::vector<int64_t>> out;
  for (int f = 0; f < frames; ++f) {
    Framebuffer fb(Options().width, Options().height);
    RenderSerial(MakeFrameContext(scene, accel, scene.path.At(f, 1.0f, scene.camera), Options()),
                 fb);
    out.emplace_back(fb.sums(), fb.sums() + 3 * fb.num_pixels());
  }
  return out;
}

TEST_CASE("registry: every backend by name, unknown and repeated names are errors") {
  const BackendRegistry r = All();
  const std::vector<std::string> want = {"serial", "lock", "lfree", "local", "tiles", "cell", "mpi"};
  CHECK(r.Names() == want);
  for (const std::string& n : want) {
    REQUIRE(r.Find(n) != nullptr);
    CHECK_FALSE(r.Find(n)->help.empty());
  }
  CHECK(r.Find("gpu") == nullptr);
  try {
    (void)r.Make("gpu", BackendConfig{});
    FAIL("unknown backend accepted");
  } catch (const Error& e) {
    const std::string what = e.what();
    CHECK(what.find("--backend gpu") != std::string::npos);
    CHECK(what.find("serial, lock, lfree, local, tiles, cell, mpi") != std::string::npos);
  }
  BackendRegistry twice;
  RegisterHostBackends(twice);
  CHECK_THROWS_AS(RegisterHostBackends(twice), Error);
  CHECK_THROWS_AS(twice.Add("", "x", nullptr), Error);
  // The factory validates: serial with two threads, a cell with nine SPEs.
  BackendConfig bad;
  bad.host.threads = 2;
  CHECK_THROWS_AS((void)r.Make("serial", bad), Error);
  BackendConfig nine;
  nine.spes = 9;
  CHECK_THROWS_AS((void)r.Make("cell", nine), Error);
}

TEST_CASE("every host backend and the cell simulator through the interface: the serial image") {
  const BackendRegistry r = All();
  const Scene scene = LoadScene("cornell");
  const Accel reference(scene.mesh());
  constexpr int kFrames = 3;
  const auto want = SerialSums(scene, reference, kFrames);
  struct Case {
    std::string name;
    int threads;
    int pbt;
    bool fixed;
    bool demand = false;  // tiles: the demand-driven master
  };
  const Case cases[] = {{"serial", 1, 0, true},  {"serial", 1, 0, false}, {"lock", 2, 0, true},
                        {"lfree", 2, 2, true},   {"local", 2, 0, true},   {"tiles", 2, 0, false},
                        {"tiles", 2, 3, true},   {"tiles", 2, 3, false, true},
                        {"cell", 1, 0, true},    {"cell", 1, 2, true}};
  for (const Case& c : cases) {
    CAPTURE(c.name);
    CAPTURE(c.pbt);
    CAPTURE(c.fixed);
    CAPTURE(c.demand);
    BackendConfig config;
    config.host.threads = c.threads;
    config.host.pbt_tiles_per_worker = c.pbt;
    config.host.pbt_demand = c.demand;
    if (c.pbt > 0 && (c.name == "lock" || c.name == "lfree" || c.name == "local")) {
      config.host.pbt_cost = PbtCost::kWork;
    }
    if (c.name == "cell") {
      config.spes = 3;
      if (c.pbt > 0) config.host.assign = PbtAssign::kCounter;
    }
    config.render = Options();
    config.fixed_sums = c.fixed;
    const auto backend = r.Make(c.name, config);
    CHECK(backend->name() == c.name);
    CHECK(backend->owns_image());
    CHECK(backend->image() == nullptr);  // allocated by the first frame
    std::optional<Accel> accel;
    std::string note = "stale";
    REQUIRE(backend->Setup([&] { accel.emplace(backend->Build(scene, {}, 40, &note)); }));
    CHECK(note.empty());
    std::vector<FrameReport> reports;
    for (int f = 0; f < kFrames; ++f) {
      backend->BeginFrame(
          MakeFrameContext(scene, *accel, scene.path.At(f, 1.0f, scene.camera), Options()));
      reports.push_back(backend->EndFrame());
      const Framebuffer* fb = backend->image();
      REQUIRE(fb != nullptr);
      REQUIRE(fb->width() == 40);
      if (fb->storage() == Framebuffer::Storage::kFixed) {
        CHECK(std::vector<int64_t>(fb->sums(), fb->sums() + 3 * fb->num_pixels()) ==
              want[static_cast<size_t>(f)]);
      } else {
        // kResolved keeps floats only: the serial image after the same conversion.
        CHECK_FALSE(c.fixed);
        Framebuffer ref(40, 30);
        std::copy(want[static_cast<size_t>(f)].begin(), want[static_cast<size_t>(f)].end(),
                  ref.sums());
        std::vector<float> rgb;
        ref.ToRgb(rgb);
        CHECK(std::vector<float>(fb->resolved().begin(), fb->resolved().end()) == rgb);
      }
      const HostFrameStats& s = reports.back().stats;
      CHECK(s.total.rays[static_cast<int>(RayKind::kPrimary)] == 40u * 30u);
      CHECK(s.total.total_seconds > 0);
      CHECK(s.threads.size() == static_cast<size_t>(c.name == "cell" ? 3 : c.threads));
      if (c.pbt > 0) {
        CHECK(s.pbt);
        CHECK(s.has_prediction == (f > 0));
      }
    }
    backend->Finish();
    CHECK_FALSE(backend->Describe().empty());
    CHECK((backend->Describe().find("demand") != std::string::npos) == c.demand);
    if (c.name == "cell") {
      CHECK(backend->Summary(reports).find("SPEs:") != std::string::npos);
      CHECK(reports[0].worker_extra.size() == 3u);
    }
    // One writer for every backend: its name, the host keys and its own fields.
    const auto dir = std::filesystem::temp_directory_path() /
                     ("rs_backend_if_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    const std::string json = (dir / "s.json").string(), csv = (dir / "s.csv").string();
    WriteFrameReports(json, scene.name, *backend, reports);
    WriteFrameReports(csv, scene.name, *backend, reports);
    const auto j = nlohmann::json::parse(std::ifstream(json));
    CHECK(j["backend"] == c.name);
    CHECK(j["options"]["name"] == c.name);
    REQUIRE(j["frames"].size() == static_cast<size_t>(kFrames));
    CHECK(j["frames"][2]["rays"]["primary"] == 40 * 30);
    if (c.pbt > 0) {
      CHECK(j["options"]["pbt_tiles_per_worker"] == c.pbt);
      CHECK(j["frames"][1].contains("pbt"));
    }
    if (c.name == "cell") {
      CHECK(j["options"]["spes"] == 3);
      CHECK(j["frames"][0]["cycles"].get<uint64_t>() > 0);
      CHECK(j["frames"][0]["threads"][2]["spe"] == 2);
    }
    std::ifstream in(csv);
    std::string header;
    std::getline(in, header);
    CHECK(header.rfind("frame,scope,index,", 0) == 0);
    CHECK((header.find(",cycles,") != std::string::npos) == (c.name == "cell"));
    std::filesystem::remove_all(dir);
  }
}

TEST_CASE("Build: the cell backend lowers lambda until the occupancy bits fit, and says so") {
  const BackendRegistry r = All();
  const Scene scene = LoadScene("spherebox");  // 49,920 triangles: 3.2 M cells at lambda 64
  BuildOptions dense;
  dense.lambda = 64;
  BackendConfig config;
  config.render = Options();
  std::string note;
  const Accel cell = r.Make("cell", config)->Build(scene, dense, 40, &note);
  CHECK(note.find("does not fit the SPE local store") != std::string::npos);
  CHECK(cell.Info().lambda < 64);
  CHECK(cell.Info().cells <= sim::OccupancyBudgetCells(sim::SimConfig{},
                                                       static_cast<uint32_t>(scene.lights.size()),
                                                       40, cell.Info().subgrids > 0));
  // A host backend builds what it is asked for, with no note.
  note = "stale";
  const Accel host = r.Make("serial", config)->Build(scene, dense, 40, &note);
  CHECK(note.empty());
  CHECK(host.Info().lambda == doctest::Approx(64));
}

}  // namespace
}  // namespace rs
