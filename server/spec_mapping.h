// interslice.v1.JobSpec (the wire) -> interslice::JobSpec (the core).
#ifndef INTERSLICE_SERVER_SPEC_MAPPING_H_
#define INTERSLICE_SERVER_SPEC_MAPPING_H_

#include <string>

#include "absl/status/statusor.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::server {

// The core spec without inputs and output folder (the server fills them in).
// INVALID_ARGUMENT naming the field for bad values; UNIMPLEMENTED for fields
// reserved for core features this build does not have yet (strict_spacing,
// derived_series, segmentation, uid_root).
absl::StatusOr<JobSpec> JobSpecFromProto(const v1::JobSpec& proto);

// "distance"/"mask"/"surface" and a media type for an artifact file name.
std::string MediaTypeForArtifact(const std::string& file_name);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_SPEC_MAPPING_H_
