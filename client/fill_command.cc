#include "client/fill_command.h"

#include "job/errors.h"
#include "job/job.h"

namespace interslice::client {

void AddFillOptions(CLI::App& app, FillArguments& args) {
  AddJobOptions(app, static_cast<job::FillJobOptions&>(args));
  AddLocalRunOptions(app, args.local);
}

int ExecuteFill(const FillArguments& args) {
  absl::StatusOr<FillJobSpec> spec = job::BuildFillJobSpec(args);
  if (!spec.ok()) {
    return FailWith(job::ForDoor(spec.status(), job::ErrorDoor::kCommandLine));
  }
  return ExecuteJob(*job::MakeFillJob(*std::move(spec)), args.local);
}

}  // namespace interslice::client
