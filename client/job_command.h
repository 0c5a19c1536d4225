// What `run` and `fill` share: their job options registered on the command
// line from the job layer's option tables (job/options.h), so every option
// has the same name, type and help on every command and in every door, and
// one way to run any kind of job in-process.
#ifndef INTERSLICE_CLIENT_JOB_COMMAND_H_
#define INTERSLICE_CLIENT_JOB_COMMAND_H_

#include <string>

#include "job/job.h"
#include "job/options.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

// Adds every option of the table that the command line takes, bound to
// `options`. A flag with an unset default (std::optional<bool>, e.g.
// rtstruct) becomes two flags, --rtstruct and --no-rtstruct, that exclude
// each other.
void AddJobOptions(CLI::App& app, job::InterpolationOptions& options);
void AddJobOptions(CLI::App& app, job::FillJobOptions& options);

// What every in-process job command also takes.
struct LocalRunArguments {
  std::string report;  // write the job's JSON report here
  int threads = 0;     // 0 = all cores
  bool quiet = false;  // no progress display or summary
};
void AddLocalRunOptions(CLI::App& app, LocalRunArguments& args);

// Runs `job` in this process with a progress display on a terminal, prints
// its warnings and summary, writes the report. Returns the exit code (0, or
// 1 with a one-line reason on stderr).
int ExecuteJob(const job::JobKind& job, const LocalRunArguments& args);

// Prints "interslice: error: <message>" on stderr; returns 1.
int FailWith(const absl::Status& status);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_JOB_COMMAND_H_
