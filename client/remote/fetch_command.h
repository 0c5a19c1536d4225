// `interslice fetch JOB --out DIR`: downloads a finished job's artifacts,
// keeping files an earlier fetch completed and resuming partial ones.
#ifndef INTERSLICE_CLIENT_REMOTE_FETCH_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_FETCH_COMMAND_H_

#include <string>

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

struct FetchArguments {
  std::string job_id;
  std::string out;
  std::string report;
  bool quiet = false;
};

CLI::App* RegisterFetch(CLI::App& app, FetchArguments& args,
                        ConnectionOptions& connection);
int RunFetch(const Connection& connection, const FetchArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_FETCH_COMMAND_H_
