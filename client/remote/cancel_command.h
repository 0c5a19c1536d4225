// `interslice cancel JOB`: asks the server to cancel a detached job.
#ifndef INTERSLICE_CLIENT_REMOTE_CANCEL_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_CANCEL_COMMAND_H_

#include <string>

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

struct CancelArguments {
  std::string job_id;
};

CLI::App* RegisterCancel(CLI::App& app, CancelArguments& args,
                         ConnectionOptions& connection);
int RunCancel(const Connection& connection, const CancelArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_CANCEL_COMMAND_H_
