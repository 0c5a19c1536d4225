// `interslice fill --server ADDR`: the fill runs on that server (one
// Interpolate call) and writes the same files as in-process; with --submit
// it is uploaded as a detached job whose id is printed (watch, fetch, list
// and cancel then work as for any job).
#ifndef INTERSLICE_CLIENT_REMOTE_FILL_REMOTE_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_FILL_REMOTE_COMMAND_H_

#include <string>

#include "client/fill_command.h"
#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

// What `fill` takes only for a server (the fill's own options are in
// FillArguments).
struct FillRemoteArguments {
  double deadline_seconds = 0;
  bool submit = false;
  std::string label;  // with --submit only
};

// Adds --server (and the other connection options), --deadline, --submit,
// --label and --send-to to `fill`, bound to `remote`, `connection` and
// `args.send_to`.
void RegisterFillRemoteOptions(CLI::App& fill, FillArguments& args,
                               FillRemoteArguments& remote,
                               ConnectionOptions& connection);

// The exit code of a parsed `fill` given --server, or of one whose
// remote-only options lack it; -1 for an in-process fill (the caller runs
// it).
int ExecuteFillRemote(const CLI::App& fill, const FillArguments& args,
                      const FillRemoteArguments& remote,
                      const ConnectionOptions& connection_options);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_FILL_REMOTE_COMMAND_H_
