#include "client/run_command.h"

#include "job/errors.h"
#include "job/job.h"

namespace interslice::client {

void AddRunOptions(CLI::App& app, RunArguments& args) {
  AddJobOptions(app, static_cast<job::InterpolationOptions&>(args));
  AddLocalRunOptions(app, args.local);
}

int ExecuteRun(const RunArguments& args) {
  absl::StatusOr<JobSpec> spec = job::BuildJobSpec(args);
  if (!spec.ok()) {
    return FailWith(job::ForDoor(spec.status(), job::ErrorDoor::kCommandLine));
  }
  return ExecuteJob(*job::MakeInterpolationJob(*std::move(spec)), args.local);
}

}  // namespace interslice::client
