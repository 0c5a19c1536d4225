// `interpolate` (one call: upload, progress, artifacts) and `submit` (a
// detached job): one file because they are one job, the one `run` runs,
// with the same options and the same upload; only the call differs.
#ifndef INTERSLICE_CLIENT_REMOTE_INTERPOLATE_SUBMIT_COMMANDS_H_
#define INTERSLICE_CLIENT_REMOTE_INTERPOLATE_SUBMIT_COMMANDS_H_

#include <string>

#include "client/grpc_channel.h"
#include "client/run_command.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

struct RemoteJobArguments {
  RunArguments run;
  double deadline_seconds = 0;
  std::string label;  // submit only
};

// Add `interpolate` / `submit` to `app`, bound to `args` and `connection`.
CLI::App* RegisterInterpolate(CLI::App& app, RemoteJobArguments& args,
                              ConnectionOptions& connection);
CLI::App* RegisterSubmit(CLI::App& app, RemoteJobArguments& args,
                         ConnectionOptions& connection);

int RunInterpolate(const Connection& connection,
                   const RemoteJobArguments& args);
int RunSubmit(const Connection& connection, const RemoteJobArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_INTERPOLATE_SUBMIT_COMMANDS_H_
