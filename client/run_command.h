// `interslice run`: the whole pipeline in-process, no server needed.
#ifndef INTERSLICE_CLIENT_RUN_COMMAND_H_
#define INTERSLICE_CLIENT_RUN_COMMAND_H_

#include <string>
#include <vector>

#include "client/job_command.h"
#include "job/options.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

// The job's options as typed (job/options.h), and what only the command
// line has.
struct RunArguments : job::InterpolationOptions {
  LocalRunArguments local;
  // Remote jobs only (interpolate, submit): DICOM peers of the server to
  // store the DICOM results on (JobSpec.send_to), and a series on a peer to
  // read instead of local files (JobSpec.pacs_source).
  std::vector<std::string> send_to;
  std::string pacs_peer, pacs_study, pacs_series;
};

// Adds the `run` subcommand's options to `app`, bound to `args`.
void AddRunOptions(CLI::App& app, RunArguments& args);

// Runs the job, shows progress on a terminal, writes the report, prints a
// summary. Returns the process exit code.
int ExecuteRun(const RunArguments& args);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_RUN_COMMAND_H_
