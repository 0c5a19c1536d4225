// libFuzzer target: untrusted bytes as a serialized interslice.v1.JobSpec,
// through the job layer's wire mapping (job/wire.h: every kind of job, the
// option tables and the core's checks), as the daemon does for every
// submitted job; an interpolation spec that passes also has its region of
// interest checked against a grid. Every outcome must be a status.
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "core/geometry/volume.h"
#include "core/pipeline/pipeline.h"
#include "google/protobuf/stubs/logging.h"
#include "interslice/v1/interslice.pb.h"
#include "job/job.h"
#include "job/wire.h"

extern "C" int LLVMFuzzerInitialize(int* argc, char*** argv) {
  // Protobuf logs every string field that is not UTF-8; a failed parse is
  // all this target needs to know, and the logging costs executions.
  google::protobuf::SetLogHandler(nullptr);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  interslice::v1::JobSpec proto;
  if (!proto.ParseFromArray(data, static_cast<int>(size))) return 0;
  (void)interslice::job::MakeJobFromWire(proto);
  auto spec = interslice::job::JobSpecFromWire(proto);
  if (!spec.ok()) return 0;
  // What the server fills in before it runs the job (JobKind::UseSpool).
  spec->inputs = {"/nonexistent/interslice-fuzz-input"};
  spec->output_dir = "/nonexistent/interslice-fuzz-output";
  if (!interslice::ValidateJobSpec(*spec).ok()) return 0;
  if (spec->roi.has_value()) {
    interslice::Grid grid;
    grid.size = {512, 512, 28};
    (void)interslice::ValidateVoxelBox(*spec->roi, grid);
  }
  return 0;
}
