// The commands that talk to an interslice-server: interpolate (one call),
// submit / watch / fetch / cancel / list (detached jobs), info and health,
// find (what a DICOM peer of the server holds), kept list / kept rerun (the
// series the server's DICOM listener holds, run again against its rules).
// Errors are one line on stderr and exit code 1. Each subcommand lives in
// client/remote/ (its options and what it does); this class registers them
// and runs the one that was parsed.
#ifndef INTERSLICE_CLIENT_REMOTE_COMMANDS_H_
#define INTERSLICE_CLIENT_REMOTE_COMMANDS_H_

#include <string>

#include "client/fill_command.h"
#include "client/grpc_channel.h"
#include "client/remote/cancel_command.h"
#include "client/remote/fetch_command.h"
#include "client/remote/fill_remote_command.h"
#include "client/remote/find_command.h"
#include "client/remote/interpolate_submit_commands.h"
#include "client/remote/kept_commands.h"
#include "client/remote/list_command.h"
#include "client/remote/watch_command.h"
#include "client/run_command.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

class RemoteCommands {
 public:
  // Adds the subcommands to `app`.
  void Register(CLI::App& app);
  // The exit code of the command that was parsed, or -1 if none of these.
  int Execute();
  // Adds --server (and the other connection options), --deadline,
  // --submit, --label and --send-to to `fill`: with --server the fill runs
  // on that server (one Interpolate call) and writes the same files as
  // in-process; with --server --submit it is uploaded as a detached job
  // whose id is printed (watch, fetch, list and cancel then work as for
  // any job). `fill` and `args` must outlive this object's use.
  void RegisterFill(CLI::App& fill, FillArguments& args);
  // The exit code of a `fill` given --server, or of one whose remote-only
  // options lack it; -1 otherwise (not parsed, or in-process: the caller
  // runs it).
  int ExecuteFill();

 private:
  // Every subcommand binds its connection options here: only one is parsed.
  ConnectionOptions connection_;
  remote::RemoteJobArguments remote_job_args_;  // interpolate and submit
  remote::WatchArguments watch_args_;
  remote::FetchArguments fetch_args_;
  remote::CancelArguments cancel_args_;
  remote::ListArguments list_args_;
  remote::FindArguments find_args_;
  remote::KeptRerunArguments kept_rerun_args_;
  remote::FillRemoteArguments fill_remote_args_;
  CLI::App* interpolate_ = nullptr;
  CLI::App* submit_ = nullptr;
  CLI::App* watch_ = nullptr;
  CLI::App* fetch_ = nullptr;
  CLI::App* cancel_ = nullptr;
  CLI::App* list_ = nullptr;
  CLI::App* info_ = nullptr;
  CLI::App* health_ = nullptr;
  CLI::App* find_ = nullptr;
  CLI::App* kept_list_ = nullptr;
  CLI::App* kept_rerun_ = nullptr;
  CLI::App* fill_ = nullptr;
  FillArguments* fill_args_ = nullptr;
};

// Whether an artifact name sent by a server is safe to use as a local path:
// "file" or "folder/file" (derived DICOM series), components of letters,
// digits, '.', '_' and '-' only, never "." or "..".
bool IsSafeArtifactName(const std::string& name);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_REMOTE_COMMANDS_H_
