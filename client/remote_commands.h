// The commands that talk to an interslice-server: interpolate (one call),
// submit / watch / fetch / cancel / list (detached jobs), info and health,
// find (what a DICOM peer of the server holds), kept list / kept rerun (the
// series the server's DICOM listener holds, run again against its rules).
// Errors are one line on stderr and exit code 1.
#ifndef INTERSLICE_CLIENT_REMOTE_COMMANDS_H_
#define INTERSLICE_CLIENT_REMOTE_COMMANDS_H_

#include <string>

#include "client/fill_command.h"
#include "client/grpc_channel.h"
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
  ConnectionOptions connection_;
  RunArguments run_args_;
  double deadline_seconds_ = 0;
  std::string label_;
  std::string job_id_;
  bool wait_deliveries_ = false;
  std::string out_;
  std::string report_;
  bool all_ = false;
  bool quiet_ = false;
  bool fill_submit_ = false;
  // find: the peer and the keys.
  std::string find_peer_;
  std::string find_patient_id_;
  std::string find_study_date_;
  std::string find_modality_;
  std::string find_accession_;
  int find_max_studies_ = 0;
  // kept rerun: one series, or every one without a job.
  std::string kept_id_;
  bool kept_all_unmatched_ = false;
  CLI::App* interpolate_ = nullptr;
  CLI::App* submit_ = nullptr;
  CLI::App* watch_ = nullptr;
  CLI::App* fetch_ = nullptr;
  CLI::App* cancel_ = nullptr;
  CLI::App* list_ = nullptr;
  CLI::App* info_ = nullptr;
  CLI::App* health_ = nullptr;
  CLI::App* find_ = nullptr;
  CLI::App* kept_ = nullptr;
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
