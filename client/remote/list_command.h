// `interslice list`: the server's detached jobs, one line each, with where
// they came from and their deliveries.
#ifndef INTERSLICE_CLIENT_REMOTE_LIST_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_LIST_COMMAND_H_

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

struct ListArguments {
  bool all = false;  // finished jobs too
};

CLI::App* RegisterList(CLI::App& app, ListArguments& args,
                       ConnectionOptions& connection);
int RunList(const Connection& connection, const ListArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_LIST_COMMAND_H_
