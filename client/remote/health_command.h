// `interslice health`: the standard gRPC health check; exit code 0 only
// when the server is SERVING.
#ifndef INTERSLICE_CLIENT_REMOTE_HEALTH_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_HEALTH_COMMAND_H_

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

CLI::App* RegisterHealth(CLI::App& app, ConnectionOptions& connection);
int RunHealth(const Connection& connection);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_HEALTH_COMMAND_H_
