// Cluster backend: master-worker rendering over MPI (Cosenza et al. §2: demand-driven tiles,
// replicated scene; §3-4: PBT re-tiling between frames). Workers return each tile's fixed-point
// sums, so the image equals the serial backend's bit for bit.
#pragma once

#include <string>

#include "sched/backend.h"
#include "sched/framebuffer.h"

namespace rs {

// The cluster backend, registered as "mpi" (sched/backend.h); run the command under `mpirun -np
// N` (N >= 2): rank 0 is the master (tiling, PBT, the framebuffer; the command writes images and
// statistics there), ranks 1..N-1 are workers. Every rank runs the command's frame loop: the
// workers' BeginFrame serves the master's tiles of that frame, their image() is nullptr.
// Its BackendConfig:
//   host.tile_width x tile_height: without PBT (host.pbt_tiles_per_worker == 0), tiles in
//     row-major order handed out on demand by a counter at the master.
//   host.pbt_tiles_per_worker k > 0: a PBT of m = k * n tiles (n = N - 1 workers), the tile plan
//     of the tiles backend (sched/tile_plan.h), updated between frames with the tile costs the
//     workers measured (host.pbt_cost: wall or CPU seconds, or the deterministic work count of
//     the tile's ray tree; with worker threads > 1 a tile's rows are split among them, which may
//     change its counts slightly, never between runs of the same configuration). Each worker
//     first takes the tiles of its own list (host.assign, host.seed); a worker whose list is
//     empty takes the last waiting tile of the list with the most predicted work left
//     (demand-driven with affinity, as SimulateDemandDriven in pbt.h models). assign counter:
//     no lists, tiles on demand by decreasing prediction.
//   host.threads: render threads inside each worker (a tile's rows are shared among them; a
//     tile's CPU time is the sum over its threads).
//   mpi_prefetch: tiles in flight per worker (1: strictly on demand; 2: the next tile waits at
//     the worker while it renders, hiding the round trip).
//   mpi_timeout_seconds: bounds every wait of the master on a worker: its setup (scene load and
//     grid build), each tile it holds (silence since it was given work or last returned a
//     result), the transfer of a result once it has begun, and its goodbye after the last frame
//     (Finish). A worker that misses it ends the run: the master prints an error naming the rank
//     and calls MPI_Abort (bounded time, never a hang).
// The frame report (host form): one "threads" entry per worker (thread = worker index = rank -
// 1), one tile record per tile (thread = the worker that rendered it, worker = PBT: the worker
// whose list held it); options() are the tiles backend's with threads = pbt_workers = workers and
// steal = true under PBT lists. Times: seconds = the frame from planning to PBT-Update on the
// master, render_seconds = first tile sent -> last result, a worker's busy / cpu = the sums of its
// tiles' wall / CPU times as it measured them, idle = render_seconds - busy, app_cpu_seconds =
// the master's CPU time in the frame. Then the cluster's own: options ranks, workers,
// worker_threads, prefetch, timeout_seconds; per frame messages, bytes (both directions, all
// workers), dropped_nan, clamped; per worker rank, messages_sent, bytes_sent (master -> worker),
// messages_received, bytes_received (worker -> master).
//
// Setup runs the command's setup on every rank and agrees on the outcome: one error line (by
// rank 0, or by the lowest failing rank when rank 0 succeeded), every rank leaves with status 1.
// A failure while rendering (a worker times out or sends a malformed result, an exception on any
// rank inside a frame) prints one line naming the rank and calls MPI_Abort, so mpirun exits
// non-zero; a backend destroyed before Finish (an error in the command, e.g. an image it cannot
// write) aborts the job too. Only complete frames reach the command, and the last one only after
// every worker has acknowledged the end of the run in Finish. A worker process that exits is
// normally noticed by mpirun first: it ends the job and names the rank (Open MPI: "Process name:
// [[job,1],r]"); the master's timeout covers workers that stay alive but silent. Apart from
// MPI_Init and MPI_Finalize the master never blocks in MPI, so a run ends within about
// mpi_timeout_seconds of a hung worker's last message. The backend calls MPI_Init (constructor)
// and MPI_Finalize (destructor) itself. Without MPI, making it throws rs::Error("--backend mpi:
// raystream was built without MPI ...") (mpi_none.cc).
//
// Hidden test hooks (environment, read by the workers; each rank r >= 1 then sleeps forever,
// except KILL):
//   RAYSTREAM_MPI_TEST_KILL_RANK=r        rank r _exit(1)s after returning its first tile;
//   RAYSTREAM_MPI_TEST_HANG_RANK=r        rank r stops answering after its first tile;
//   RAYSTREAM_MPI_TEST_HANG_SETUP_RANK=r  rank r hangs before loading the scene;
//   RAYSTREAM_MPI_TEST_HANG_END_RANK=r    rank r hangs after its last tile (at the stop message);
//   RAYSTREAM_MPI_TEST_STALL_RANK=r       rank r starts sending its first result (MPI_Isend)
//                                         and never makes MPI progress again.
void RegisterMpiBackend(BackendRegistry& registry);

// True when raystream was built with MPI (meson option 'mpi' found an MPI library).
bool MpiBuilt();

// Hidden --dump-raw format, for exact comparisons between backends: "RSFB" (4 bytes), int32
// width, int32 height (little endian, host order), then width * height * 3 int64 sums.
// Written atomically (scenes/image_io.h). Throws rs::Error naming the path.
void WriteRawFramebuffer(const std::string& path, const Framebuffer& fb);
// The file's bytes, for staging.
std::string RawFramebufferBytes(const Framebuffer& fb);

}  // namespace rs
