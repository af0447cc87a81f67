// Cluster backend: master-worker rendering over MPI (Cosenza et al. §2: demand-driven tiles,
// replicated scene; §3-4: PBT re-tiling between frames). Workers return each tile's fixed-point
// sums, so the image equals the serial backend's bit for bit.
#pragma once

#include <cstdint>
#include <string>

#include "sched/backends.h"  // PbtAssign, PbtCost (sched/tile_plan.h)
#include "sched/framebuffer.h"
#include "sched/render.h"

namespace rs {

// Everything `raystream render --backend mpi` needs; every rank gets the same values (the same
// command line under mpirun).
struct MpiRenderConfig {
  std::string scene;
  RenderOptions options;  // width, height, max_depth, task_size, weight_cutoff, order
  float lambda = 0;       // grid density (BuildOptions::lambda); <= 0: the default
  int frames = 1;
  float speed = 1.0f;
  std::string out;  // image pattern ('#' = frame number, every frame); empty: SCENE.png
  // Per-frame statistics, .json or .csv (empty: none), written by the host backends' writer
  // (WriteHostStats) in their format: one "threads" entry / thread row per worker (thread =
  // worker index = rank - 1), one tile record per tile (thread = the worker that rendered it,
  // worker = PBT: the worker whose list held it), the PBT fields, backend "mpi", options as the
  // tiles backend's with pbt_workers = workers and steal = true under PBT lists. Times: seconds =
  // the frame from planning to PBT-Update on the master, render_seconds = first tile sent -> last
  // result, a worker's busy / cpu = the sums of its tiles' wall / CPU times as it measured them,
  // idle = render_seconds - busy, app_cpu_seconds = the master's CPU time in the frame. Then the
  // cluster's own (CSV: columns after the host columns): options ranks, workers,
  // worker_threads, prefetch, timeout_seconds; per frame messages, bytes (both directions, all
  // workers), dropped_nan, clamped; per worker rank, messages_sent, bytes_sent (master ->
  // worker), messages_received, bytes_received (worker -> master).
  std::string stats;
  std::string dump_raw;  // hidden: raw fixed-point framebuffer per written frame ('#' allowed)
  // Without PBT (pbt_tiles_per_worker == 0): tile_width x tile_height tiles in row-major order,
  // handed out on demand by a counter at the master.
  int tile_width = 32;
  int tile_height = 32;
  // k > 0: a PBT of m = k * n tiles (n = ranks - 1 workers), the tile plan of the tiles
  // backend (sched/tile_plan.h), updated between frames with the tile costs the workers measured
  // (pbt_cost: wall or CPU seconds, or the deterministic work count of the tile's ray tree;
  // with worker threads > 1 a tile's rows are split among them, which may change its counts
  // slightly, never between runs of the same configuration). Each worker first takes the tiles
  // of its own list (assign); a worker whose list is empty takes the last waiting tile of the
  // list with the most predicted work left (demand-driven with affinity, as SimulateDemandDriven
  // in pbt.h models). assign counter: no lists, tiles on demand by decreasing prediction.
  int pbt_tiles_per_worker = 0;
  PbtAssign assign = PbtAssign::kRandom;
  uint64_t seed = 1;
  PbtCost pbt_cost = PbtCost::kWall;
  // Render threads inside each worker (--threads): a tile's rows are shared among them. A
  // tile's CPU time is the sum over its threads.
  int threads = 1;
  // Tiles in flight per worker (1: strictly on demand; 2: the next tile waits at the worker
  // while it renders, hiding the round trip).
  int prefetch = 2;
  // Bounds every wait of the master on a worker: its setup (scene load and grid build), each
  // tile it holds (silence since it was given work or last returned a result), the transfer of
  // a result once it has begun, and its goodbye after the last frame. A worker that misses it
  // ends the run: the master prints an error naming the rank and calls MPI_Abort (bounded time,
  // never a hang).
  double timeout_seconds = 120;
  bool quiet = false;
};

// True when raystream was built with MPI (meson option 'mpi' found an MPI library).
bool MpiBuilt();

// Runs the whole render on this rank; call it from every rank of `mpirun -np N` (N >= 2): rank 0
// is the master (tiling, framebuffer, images, statistics), ranks 1..N-1 are workers. Calls
// MPI_Init and MPI_Finalize itself. Returns the process exit status: 0 on success; 1 after a
// setup error (bad option, scene, too few ranks), printed once (by the lowest failing rank) and
// returned by every rank. A failure while
// rendering (a worker times out or sends a malformed result, an exception on any rank) prints
// one line naming the rank and calls MPI_Abort, so mpirun exits non-zero; images are written
// only for complete frames, and the last frame's image and the statistics only after every
// worker has acknowledged the end of the run (so a failed run leaves neither). A worker process
// that exits is normally noticed by mpirun first: it ends the job and names the rank (Open MPI:
// "Process name: [[job,1],r]"); the master's timeout covers workers that stay alive but silent
// (hung while loading, rendering, sending or finishing, or lost where the launcher does not
// notice). Apart from MPI_Init and MPI_Finalize (reached after every worker's goodbye) the
// master never blocks in MPI, so a run ends within about timeout_seconds of a hung worker's
// last message. Without MPI: throws rs::Error("raystream was built without MPI")
// (mpi_none.cc).
//
// Hidden test hooks (environment, read by the workers; each rank r >= 1 then sleeps forever,
// except KILL):
//   RAYSTREAM_MPI_TEST_KILL_RANK=r        rank r _exit(1)s after returning its first tile;
//   RAYSTREAM_MPI_TEST_HANG_RANK=r        rank r stops answering after its first tile;
//   RAYSTREAM_MPI_TEST_HANG_SETUP_RANK=r  rank r hangs before loading the scene;
//   RAYSTREAM_MPI_TEST_HANG_END_RANK=r    rank r hangs after its last tile (at the stop message);
//   RAYSTREAM_MPI_TEST_STALL_RANK=r       rank r starts sending its first result (MPI_Isend)
//                                         and never makes MPI progress again.
int RunMpiRender(const MpiRenderConfig& config);

// Hidden --dump-raw format, for exact comparisons between backends: "RSFB" (4 bytes), int32
// width, int32 height (little endian, host order), then width * height * 3 int64 sums.
// Written through a temporary name and renamed. Throws rs::Error naming the path.
void WriteRawFramebuffer(const std::string& path, const Framebuffer& fb);

}  // namespace rs
