// The cluster backend when raystream is built without MPI (meson option 'mpi' found nothing):
// `--backend mpi` is registered and fails with one clear error instead of a missing symbol.
#include "include/raystream/raystream.h"
#include "sched/mpi_backend.h"

namespace rs {

void RegisterMpiBackend(BackendRegistry& registry) {
  registry.Add("mpi", "master-worker over MPI ranks (not built: no MPI library)",
               [](const BackendConfig&) -> std::unique_ptr<Backend> {
                 throw Error(
                     "--backend mpi: raystream was built without MPI (install an MPI library "
                     "such as libopenmpi-dev and reconfigure with -Dmpi=enabled)");
               });
}

}  // namespace rs
