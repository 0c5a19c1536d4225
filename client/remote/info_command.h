// `interslice info`: the server's version, limits, methods, outputs, RPCs
// and transfer syntaxes.
#ifndef INTERSLICE_CLIENT_REMOTE_INFO_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_INFO_COMMAND_H_

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

CLI::App* RegisterInfo(CLI::App& app, ConnectionOptions& connection);
int RunInfo(const Connection& connection);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_INFO_COMMAND_H_
