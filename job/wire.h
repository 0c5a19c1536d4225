// The wire spec (interslice.v1.JobSpec, what the CLI's remote commands send,
// the DICOM node's rules hold and the server runs) <-> the core specs. Both
// directions go through the option tables of job/options.h: the wire is read
// into the same option values a person would type, and checked by the same
// BuildJobSpec / BuildFillJobSpec, so every door accepts and refuses the
// same jobs. Errors name the wire field ("spec.energy_units: ...").
//
// Inputs, segmentation, output folder and the server's limits are not
// carried: the server supplies them.
#ifndef INTERSLICE_JOB_WIRE_H_
#define INTERSLICE_JOB_WIRE_H_

#include <string>

#include "absl/status/statusor.h"
#include "core/labels/fill_job.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"
#include "job/options.h"

namespace interslice::job {

// A fill job is a wire spec with `fill` set; any other is an interpolation.
inline bool IsFillSpec(const v1::JobSpec& spec) { return spec.has_fill(); }

// SUCCEEDED, FAILED or CANCELLED: the job will not change again.
inline bool IsTerminalState(v1::JobState state) {
  return state == v1::JOB_STATE_SUCCEEDED || state == v1::JOB_STATE_FAILED ||
         state == v1::JOB_STATE_CANCELLED;
}

// Every option as given (send_to and pacs_source are not options: the
// caller adds them).
v1::JobSpec ToWire(const JobSpec& spec);
// A fill job, with `segmentation_file` as the FileChunk.file_name under which
// the segmentation is uploaded and `label_names_file` (empty: none) that of
// its label names (spec.label_names, a local path, is not sent).
v1::JobSpec ToWire(const FillJobSpec& spec,
                   const std::string& segmentation_file,
                   const std::string& label_names_file = "");

// The option values a wire spec gives (errors name the wire field: unknown
// enum values, fields that do not belong to this kind of job).
absl::StatusOr<InterpolationOptions> InterpolationOptionsFromWire(
    const v1::JobSpec& spec);
absl::StatusOr<FillJobOptions> FillOptionsFromWire(const v1::JobSpec& spec);

// The core spec without inputs, segmentation and output folder, checked as
// every door checks it; INVALID_ARGUMENT naming the wire field.
absl::StatusOr<JobSpec> JobSpecFromWire(const v1::JobSpec& spec);
absl::StatusOr<FillJobSpec> FillJobSpecFromWire(const v1::JobSpec& spec);

}  // namespace interslice::job

#endif  // INTERSLICE_JOB_WIRE_H_
