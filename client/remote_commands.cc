#include "client/remote_commands.h"

#include <string>

#include "CLI/CLI.hpp"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "client/remote/health_command.h"
#include "client/remote/info_command.h"
#include "client/remote/remote_common.h"

namespace interslice::client {

void RemoteCommands::Register(CLI::App& app) {
  // The order of the subcommands in `interslice --help`.
  interpolate_ =
      remote::RegisterInterpolate(app, remote_job_args_, connection_);
  submit_ = remote::RegisterSubmit(app, remote_job_args_, connection_);
  watch_ = remote::RegisterWatch(app, watch_args_, connection_);
  fetch_ = remote::RegisterFetch(app, fetch_args_, connection_);
  cancel_ = remote::RegisterCancel(app, cancel_args_, connection_);
  list_ = remote::RegisterList(app, list_args_, connection_);
  info_ = remote::RegisterInfo(app, connection_);
  health_ = remote::RegisterHealth(app, connection_);
  find_ = remote::RegisterFind(app, find_args_, connection_);
  const remote::KeptSubcommands kept =
      remote::RegisterKept(app, kept_rerun_args_, connection_);
  kept_list_ = kept.list;
  kept_rerun_ = kept.rerun;
}

void RemoteCommands::RegisterFill(CLI::App& fill, FillArguments& args) {
  fill_ = &fill;
  fill_args_ = &args;
  remote::RegisterFillRemoteOptions(fill, args, fill_remote_args_, connection_);
}

int RemoteCommands::ExecuteFill() {
  if (fill_ == nullptr || !fill_->parsed()) return -1;
  return remote::ExecuteFillRemote(*fill_, *fill_args_, fill_remote_args_,
                                   connection_);
}

int RemoteCommands::Execute() {
  CLI::App* commands[] = {interpolate_, submit_,    watch_,     fetch_,
                          cancel_,      list_,      info_,      health_,
                          find_,        kept_list_, kept_rerun_};
  bool any = false;
  for (CLI::App* c : commands) any = any || (c != nullptr && c->parsed());
  if (!any) return -1;
  // What needs no server is checked before connecting.
  if (remote_job_args_.deadline_seconds < 0) {
    return remote::Fail("--deadline must be >= 0");
  }
  if (kept_rerun_->parsed()) {
    if (absl::Status s = remote::CheckKeptRerun(kept_rerun_args_); !s.ok()) {
      return remote::Fail(std::string(s.message()));
    }
  }
  absl::StatusOr<Connection> connection = Connection::Open(connection_);
  if (!connection.ok()) {
    return remote::Fail(std::string(connection.status().message()));
  }
  if (kept_list_->parsed()) return remote::RunKeptList(*connection);
  if (kept_rerun_->parsed()) {
    return remote::RunKeptRerun(*connection, kept_rerun_args_);
  }
  if (interpolate_->parsed()) {
    return remote::RunInterpolate(*connection, remote_job_args_);
  }
  if (submit_->parsed()) {
    return remote::RunSubmit(*connection, remote_job_args_);
  }
  if (watch_->parsed()) return remote::RunWatch(*connection, watch_args_);
  if (fetch_->parsed()) return remote::RunFetch(*connection, fetch_args_);
  if (cancel_->parsed()) return remote::RunCancel(*connection, cancel_args_);
  if (list_->parsed()) return remote::RunList(*connection, list_args_);
  if (info_->parsed()) return remote::RunInfo(*connection);
  if (find_->parsed()) return remote::RunFind(*connection, find_args_);
  return remote::RunHealth(*connection);
}

}  // namespace interslice::client
