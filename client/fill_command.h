// `interslice fill`: a segmentation (label map, DICOM SEG or RTSTRUCT) drawn
// on some slices of a reference DICOM series, filled between its key slices
// for every label, in-process (core/labels/fill_job.h).
#ifndef INTERSLICE_CLIENT_FILL_COMMAND_H_
#define INTERSLICE_CLIENT_FILL_COMMAND_H_

#include <string>
#include <vector>

#include "client/job_command.h"
#include "job/options.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

// The fill's options as typed (job/options.h), and what only the command
// line has.
struct FillArguments : job::FillJobOptions {
  LocalRunArguments local;
  // With --server only: DICOM peers of the server to store the DICOM
  // results on (JobSpec.send_to).
  std::vector<std::string> send_to;
};

void AddFillOptions(CLI::App& app, FillArguments& args);

// Runs the job, prints warnings and a summary. Returns the exit code.
int ExecuteFill(const FillArguments& args);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_FILL_COMMAND_H_
