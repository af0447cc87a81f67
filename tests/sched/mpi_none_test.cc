// The cluster backend of a build without MPI (sched/mpi_none.cc, compiled into this test in every
// build, with MPI or without): `--backend mpi` is registered, and making it is one clear
// rs::Error naming the option and the fix, for any configuration, never a missing symbol, an MPI
// call or a crash.
#include <doctest/doctest.h>

#include <string>

#include "include/raystream/raystream.h"
#include "sched/backend.h"
#include "sched/mpi_backend.h"

namespace rs {
namespace {

TEST_CASE("without MPI, --backend mpi throws rs::Error: built without MPI, how to fix it") {
  BackendRegistry registry;
  RegisterMpiBackend(registry);
  REQUIRE(registry.Find("mpi") != nullptr);
  BackendConfig walk;  // what `mpirun -np 5 raystream render --backend mpi ...` would pass
  walk.scene = "cornell";
  walk.host.pbt_tiles_per_worker = 2;
  walk.host.assign = PbtAssign::kGreedy;
  BackendConfig invalid;  // rejected by the MPI build's checks; here the missing MPI comes first
  invalid.mpi_timeout_seconds = -1;
  invalid.render.width = 0;
  for (const BackendConfig& config : {walk, invalid, BackendConfig{}}) {
    std::string what;
    bool made = false;
    try {
      made = registry.Make("mpi", config) != nullptr;
    } catch (const Error& e) {
      what = e.what();
    }
    INFO("error: ", what);
    CHECK_FALSE(made);
    CHECK(what.rfind("--backend mpi: ", 0) == 0);  // names the option first
    CHECK(what.find("raystream was built without MPI") != std::string::npos);
    CHECK(what.find("-Dmpi=enabled") != std::string::npos);  // and the fix
    CHECK(what.find('\n') == std::string::npos);  // one line
  }
}

}  // namespace
}  // namespace rs
