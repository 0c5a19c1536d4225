// The core job spec -> interslice.v1.JobSpec (the wire), as the client's
// remote commands send it and as the server's DICOM rules build it (the
// inverse of server/spec_mapping.h). Inputs and the output folder are not
// carried: the server supplies them.
#ifndef INTERSLICE_CLIENT_JOB_SPEC_PROTO_H_
#define INTERSLICE_CLIENT_JOB_SPEC_PROTO_H_

#include <string>

#include "core/labels/fill_job.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::client {

// Every field is carried as given; the server validates (JobSpecFromProto).
v1::JobSpec JobSpecToProto(const JobSpec& spec);

// A fill job (`interslice fill --server`, DICOM rules with `fill:`): the
// spec's fill options, with `segmentation_file` as the FileChunk.file_name
// under which the segmentation is uploaded. Its reference, segmentation and
// output folder are not carried.
v1::JobSpec FillJobSpecToProto(const FillJobSpec& spec,
                               const std::string& segmentation_file);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_JOB_SPEC_PROTO_H_
