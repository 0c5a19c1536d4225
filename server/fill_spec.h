// Fill jobs on the server (issue 13): interslice.v1.JobSpec with `fill` set
// (the wire) -> FillJobSpec (core/labels/fill_job.h), where such a job's
// files live in the spool, and its report as the job manager needs it.
//
// In the job's upload folder (spool/jobs/<id>/upload/) the reference series
// is every regular file directly in the folder (named by index, as for
// interpolation jobs) and the segmentation is the one file in its
// subfolder segmentation/ (named by the server, with the extension of the
// client's name, which selects label map or DICOM reader). Keeping it out of
// the folder's top level keeps a SEG or RTSTRUCT from being read as part of
// the reference series.
#ifndef INTERSLICE_SERVER_FILL_SPEC_H_
#define INTERSLICE_SERVER_FILL_SPEC_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/labels/fill_job.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::server {

inline bool IsFillJob(const v1::JobSpec& spec) { return spec.has_fill(); }

// The core spec without reference, segmentation and output folder (the
// server fills them in). INVALID_ARGUMENT naming the field ("spec.fill.labels:
// 0 is not a label (1..65535)", "spec.threshold is not used by fill jobs").
absl::StatusOr<FillJobSpec> FillJobSpecFromProto(const v1::JobSpec& proto);

// The path, relative to the job's upload folder, where the uploaded
// segmentation is stored: "segmentation/segmentation" + the extension of
// `client_file_name` (".nii", ".nii.gz", ".nrrd"; anything else ".dcm").
std::string SegmentationUploadPath(const std::string& client_file_name);

// Fills in spec->reference (the regular files directly in `upload_dir`,
// sorted) and spec->segmentation (the one file in upload_dir/segmentation).
// FAILED_PRECONDITION when either is missing.
absl::Status SetFillInputs(const std::string& upload_dir, FillJobSpec* spec);

// Runs the fill job of `proto` on the upload folder into `output_dir`
// (max_output_voxels > 0 replaces the default limit). Returns the report as
// FillJobReportToJson writes it (artifact paths absolute).
absl::StatusOr<std::string> RunFillJobInSpool(const v1::JobSpec& proto,
                                              const std::string& upload_dir,
                                              const std::string& output_dir,
                                              int64_t max_output_voxels,
                                              const ComputeContext& context);

// What the job manager takes from a fill report: the stage timings, the
// artifacts (kind, absolute path) and the report with every artifact path
// replaced by its bare file name (as clients get it).
struct FillReportSummary {
  std::vector<StageTiming> stages;
  std::vector<Artifact> artifacts;
  std::string report_json;
};
// INTERNAL for JSON that FillJobReportToJson did not write.
absl::StatusOr<FillReportSummary> SummarizeFillReport(const std::string& json);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_FILL_SPEC_H_
