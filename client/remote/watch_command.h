// `interslice watch JOB`: follows a detached job until it ends, reconnecting
// after network failures; with --wait-deliveries also until its DICOM
// deliveries end.
#ifndef INTERSLICE_CLIENT_REMOTE_WATCH_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_WATCH_COMMAND_H_

#include <string>

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

struct WatchArguments {
  std::string job_id;
  bool quiet = false;
  bool wait_deliveries = false;
};

CLI::App* RegisterWatch(CLI::App& app, WatchArguments& args,
                        ConnectionOptions& connection);
int RunWatch(const Connection& connection, const WatchArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_WATCH_COMMAND_H_
