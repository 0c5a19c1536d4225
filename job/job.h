// The kinds of job (interpolation, fill) behind one interface, so that the
// CLI, the server's job manager and worker processes and the DICOM node's
// rules run any job without knowing which kind it is.
//
// A job is made from a core spec (the CLI, in-process) or from the wire spec
// (the server), pointed at its files, and run with progress and
// cancellation (core/common/compute.h). What it made comes back in one
// report shape, JobResult: the stages with their times, the artifacts, and
// the kind's own detailed report as JSON.
#ifndef INTERSLICE_JOB_JOB_H_
#define INTERSLICE_JOB_JOB_H_

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/common/compute.h"
#include "core/labels/fill_job.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::job {

// What a job made, the same for every kind.
struct JobResult {
  // Stage names and seconds, in the order they ran.
  std::vector<StageTiming> stages;
  // kind, path, size: files, or a folder for a derived DICOM series. Paths
  // are where the job wrote them (absolute when its output folder was).
  std::vector<Artifact> artifacts;
  // The kind's own report (core/pipeline JobReportToJson, core/labels
  // FillJobReportToJson). With JobKind::UseSpool its artifact paths are
  // relative to the output folder (a client must not learn the server's
  // paths); otherwise as written.
  std::string report_json;
  // For a person: a few lines that say what was made (no patient data).
  std::vector<std::string> summary;
  // Things the person should know although the job succeeded.
  std::vector<std::string> warnings;
  // Peak resident set size of the process that ran the job, bytes
  // (core/pipeline PeakRssBytes, VmHWM): the CLI's own process for
  // `interslice run`/`fill` (not its parent's), the worker process for a
  // server job in one (as the worker measured itself), the whole server
  // process since it started for a job run in the server (--isolation
  // thread), where a job's own share is not measurable. -1 when unknown.
  int64_t peak_rss_bytes = 0;
};

// A file of a job's upload that is not part of its series: the name it
// arrives under and where the server keeps it.
struct NamedUpload {
  // The wire field that names the file, for errors
  // ("spec.fill.segmentation_file").
  std::string field;
  // FileChunk.file_name as the client sent it (compared exactly), or the
  // name the DICOM node's rule gives a received file. May carry patient data:
  // never logged or echoed.
  std::string client_name;
  // Where the file is stored, relative to the upload folder: always below a
  // subfolder, never at the top level where the series' files are read.
  std::string path;
};

class JobKind {
 public:
  virtual ~JobKind() = default;

  // "interpolate" or "fill".
  virtual absl::string_view name() const = 0;

  // Admission (server): the fewest files an upload of this job can hold
  // (a fill job uploads its segmentation and its reference series).
  virtual int min_upload_files() const = 0;
  // Whether the job writes DICOM results (needed to deliver to a peer).
  virtual bool writes_dicom() const = 0;
  // The uploaded files the job takes by name rather than as part of its
  // series (a fill's segmentation and label names), each exactly once; empty
  // for kinds without any. Every door that fills a job's upload folder (the
  // gRPC upload, the DICOM node's received files) stores them where these
  // say, and UseSpool reads them from there.
  virtual std::vector<NamedUpload> named_uploads() const { return {}; }

  // Points the job at a server's spool: it reads its files from
  // `upload_dir` (series files at its top level, each named upload at its
  // path) and writes into `output_dir`; max_output_voxels > 0 replaces the
  // core's default limit. The report's artifact paths become relative to
  // `output_dir`. FAILED_PRECONDITION when the files the job needs are not
  // there.
  virtual absl::Status UseSpool(const std::string& upload_dir,
                                const std::string& output_dir,
                                int64_t max_output_voxels) = 0;

  // For a job whose DICOM objects are all it delivers (a DICOM node's job
  // that sends its results to PACS peers, server/engine/spool.h
  // DeliversOnlyDicomToPeers): files whose content those objects carry are
  // not written (core/pipeline JobSpec::omit_files_dicom_objects_carry).
  // Kinds that write no such files ignore it.
  virtual void OmitFilesDicomObjectsCarry() {}

  // Runs the job. Errors from the core (each stage's header says which);
  // CANCELLED / DEADLINE_EXCEEDED when context.cancel fires.
  virtual absl::StatusOr<JobResult> Run(
      const ComputeContext& context) const = 0;
};

// The human summary's line for a job's region of interest: the voxel box
// and, when it was given in mm, the box as given ("  region    voxels x
// 234..323, y 49..138, z 0..4 (half-open) from the box (-10, 20, 690)..(30,
// 60, 720) LPS mm"); nullopt for the whole series. Used by the in-process
// summary and by the remote commands (from the report JSON).
std::optional<std::string> RegionSummaryLine(const JobReport& report);

// A job for the core spec as given (inputs and output folder included).
std::unique_ptr<JobKind> MakeInterpolationJob(JobSpec spec);
std::unique_ptr<JobKind> MakeFillJob(FillJobSpec spec);

// The job a wire spec names (fill when spec.fill is set), checked as every
// door checks it (job/wire.h); INVALID_ARGUMENT naming the wire field. Its
// files are set by UseSpool.
absl::StatusOr<std::unique_ptr<JobKind>> MakeJobFromWire(
    const v1::JobSpec& spec);

// Where a job's uploaded segmentation is stored, relative to its upload
// folder: "segmentation/segmentation" + the extension of `client_name`
// (".nii", ".nii.gz", ".nrrd"; anything else ".dcm", which selects the
// DICOM reader). Kept out of the folder's top level so that a SEG or
// RTSTRUCT is never read as part of the reference series.
std::string SegmentationUploadPath(const std::string& client_name);

// Where a job's uploaded label names (a colour table or JSON sidecar,
// core/labels/segment_names.h) are stored, beside the segmentation:
// "segmentation/label-names" + the extension of `client_name` (".csv",
// ".txt" or ".json", which selects the reader; the wire check refuses
// any other).
std::string LabelNamesUploadPath(const std::string& client_name);

// The series a job reads, from its files' headers (never pixel data), for
// a job's status. Carries UIDs: for the job's owner, never for logs.
struct SourceSeries {
  std::string study_instance_uid;
  std::string series_instance_uid;  // or "no-uid-N" (core/dicom)
  std::string modality;
  // Files of the series (a multi-frame instance counts once).
  int64_t instance_count = 0;
};

// The series at the top level of `upload_dir` (where UseSpool reads a job's
// series) that `series_uid` names (JobSpec.series_instance_uid; empty = the
// only one): the reader's own choice (core/dicom/series_index.h
// FindDicomSeries), so that it is the series the job reads. Its errors
// (NOT_FOUND, FAILED_PRECONDITION) when the folder holds none, several or
// not that one; the job's own read then says the same.
absl::StatusOr<SourceSeries> DescribeSourceSeries(
    const std::string& upload_dir, const std::string& series_uid,
    const ComputeContext& context);

// "distance"/"mask"/... file name -> its media type (application/dicom,
// model/stl, ...).
std::string MediaTypeForArtifact(const std::string& file_name);

}  // namespace interslice::job

#endif  // INTERSLICE_JOB_JOB_H_
