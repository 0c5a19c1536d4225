// `interslice kept list` / `kept rerun`: the series the server's DICOM
// listener holds (no rule matched, or their job was made), and running
// them again against its rules (admins only).
#ifndef INTERSLICE_CLIENT_REMOTE_KEPT_COMMANDS_H_
#define INTERSLICE_CLIENT_REMOTE_KEPT_COMMANDS_H_

#include <string>

#include "absl/status/status.h"
#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

// kept rerun: one series, or every one without a job.
struct KeptRerunArguments {
  std::string id;
  bool all_unmatched = false;
};

struct KeptSubcommands {
  CLI::App* list = nullptr;
  CLI::App* rerun = nullptr;
};

// Adds `kept` (which requires one of its subcommands) to `app`.
KeptSubcommands RegisterKept(CLI::App& app, KeptRerunArguments& rerun_args,
                             ConnectionOptions& connection);

// What `kept rerun` needs before connecting: an id or --all-unmatched, not
// both.
absl::Status CheckKeptRerun(const KeptRerunArguments& args);

// One line per kept series: id, since when, from whom, what, why (UIDs
// included: only admins are answered).
int RunKeptList(const Connection& connection);

// One line per series run again: "job ID" for each job made, "not matched
// ID: why" for each series no rule takes (not an error).
int RunKeptRerun(const Connection& connection, const KeptRerunArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_KEPT_COMMANDS_H_
