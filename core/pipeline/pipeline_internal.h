// Private to core/pipeline: the stages of RunJob (pipeline.h).
// pipeline.cc runs them in order; pipeline_stages.cc holds read, contour,
// stack, solve, mesh, the Encapsulated STL's mesh and the previews;
// pipeline_write.cc the write stage.
#ifndef INTERSLICE_CORE_PIPELINE_PIPELINE_INTERNAL_H_
#define INTERSLICE_CORE_PIPELINE_PIPELINE_INTERNAL_H_

#include <algorithm>
#include <chrono>
#include <future>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/series_reader.h"
#include "core/geometry/volume.h"
#include "core/morph/intensity_morph.h"
#include "core/pipeline/pipeline.h"
#include "core/preview/preview.h"
#include "core/stack/stacking.h"
#include "core/surface/surface.h"

namespace interslice::pipeline_internal {

// Reports a stage's start (fraction 0) when made, and records its time in
// the job report when it goes.
class StageClock {
 public:
  StageClock(JobReport& report, const ComputeContext& context,
             std::string stage)
      : report_(report),
        stage_(std::move(stage)),
        start_(std::chrono::steady_clock::now()) {
    context.Report({.stage = stage_, .fraction = 0});
  }
  ~StageClock() {
    const std::chrono::duration<double> elapsed =
        std::chrono::steady_clock::now() - start_;
    report_.stages.push_back({stage_, elapsed.count()});
  }

 private:
  JobReport& report_;
  std::string stage_;
  std::chrono::steady_clock::time_point start_;
};

inline bool Contains(const std::vector<std::string>& list,
                     const std::string& item) {
  return std::find(list.begin(), list.end(), item) != list.end();
}

// Which results the job writes, beyond the files of its formats.
struct WantedOutputs {
  bool seg = false;           // the SEG (write_seg or output series "mask")
  bool distance_map = false;  // the Parametric Map
  // The intensity series: asked for, or brought along by a SEG or a
  // distance map, which reference it (JobSpec::output_series).
  bool intensity = false;
  bool previews = false;
  // The Encapsulated STL: DICOM outputs with mesh format "stl".
  bool dicom_mesh = false;
};

// The source series as the job uses it.
struct SourceSlices {
  // The grey values of the slices used (a region of interest cropped), on
  // their own grid; released once no stage needs them.
  Volume<float> image;
  // The series' metadata (slices, UIDs, grid) for DICOM outputs; its voxels
  // are moved out into `image`.
  DicomSeries source;
  std::vector<double> positions;  // of the slices used, mm along the normal
};

// The intensity series' values while the solve, mesh and preview stages run
// (see StartIntensityMorph).
struct PendingIntensity {
  std::optional<float> padding;  // the source's pixel padding
  // Set for intensity_method "morph": MorphIntensity on its own thread.
  std::future<absl::StatusOr<MorphedIntensity>> morphing;
};

// The Encapsulated STL's mesh (JobSpec::dicom_mesh_adaptivity and
// dicom_mesh_max_mb), made beside the preview and write stages (see
// StartDicomMesh). `done` is declared last, so it is destroyed (waiting for
// the thread) before what the thread writes.
struct PendingDicomMesh {
  Mesh storage;                // its own mesh, when it is not the surface
  const Mesh* mesh = nullptr;  // the mesh to store: &storage or the surface
  double seconds = -1;         // -1: no dicom-mesh stage
  std::future<absl::Status> done;
};

// The stages, in the order RunJob runs them. Each stage with a StageClock
// reports its start and records its time.

// read: the series (or its region of interest). INVALID_ARGUMENT for fewer
// than 2 slices.
absl::StatusOr<SourceSlices> ReadSourceStage(const JobSpec& spec,
                                             JobReport& report,
                                             const ComputeContext& context);

// contour: the 2D signed distance maps of the original slices (or of their
// slab deconvolution). Releases input.image unless an intensity series or
// the previews need it.
absl::StatusOr<Volume<float>> ContourStage(const JobSpec& spec,
                                           const WantedOutputs& wants,
                                           SourceSlices& input,
                                           JobReport& report,
                                           const ComputeContext& context);

// stack: the maps on the output grid (linear, or the morph for method
// morph); `slice_maps` is released before the stage ends.
absl::StatusOr<StackedField> StackStage(const JobSpec& spec,
                                        const std::vector<double>& positions,
                                        Volume<float> slice_maps,
                                        JobReport& report,
                                        const ComputeContext& context);

// Starts MorphIntensity of `image` onto `grid` on its own thread; `image`
// and `positions` must outlive the future.
std::future<absl::StatusOr<MorphedIntensity>> StartIntensityMorph(
    const Volume<float>& image, const std::vector<double>& positions,
    const Grid& grid, std::optional<float> padding,
    const ComputeContext& context);

// solve: refines the stacked field in place.
absl::Status SolveStage(const JobSpec& spec, StackedField& stacked,
                        JobReport& report, const ComputeContext& context);

// mesh: the surface of the field.
absl::StatusOr<Mesh> MeshStage(const JobSpec& spec, const Volume<float>& field,
                               JobReport& report,
                               const ComputeContext& context);

// Starts making the Encapsulated STL's mesh into `dicom_mesh` on its own
// thread; everything it reads or writes (dicom_mesh included) must outlive
// dicom_mesh.done.
void StartDicomMesh(const JobSpec& spec, const DicomSeries& source,
                    const Mesh& mesh, const Volume<float>& field,
                    JobReport& report, PendingDicomMesh& dicom_mesh,
                    const ComputeContext& context);

// preview: the rendered previews, or none (a failure is a note in the
// report, never the job's failure); CANCELLED / DEADLINE_EXCEEDED from the
// context. Releases input.image unless the intensity series needs it.
absl::StatusOr<std::optional<PreviewSet>> PreviewStage(
    const JobSpec& spec, const WantedOutputs& wants, SourceSlices& input,
    const Volume<float>& field, JobReport& report,
    const ComputeContext& context);

// write: every result into spec.output_dir, recorded in report.artifacts.
// Releases input.image.
absl::Status WriteStage(const JobSpec& spec, const WantedOutputs& wants,
                        SourceSlices& input, const Volume<float>& field,
                        const Mesh& mesh,
                        const std::optional<PreviewSet>& previews,
                        PendingIntensity& intensity,
                        PendingDicomMesh& dicom_mesh, JobReport& report,
                        const ComputeContext& context);

}  // namespace interslice::pipeline_internal

#endif  // INTERSLICE_CORE_PIPELINE_PIPELINE_INTERNAL_H_
