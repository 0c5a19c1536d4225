// What a finished job made, as its status lists it (JobStatus.artifacts) and
// as its deliveries send it: the job manager's view of a job's artifacts
// (server/engine/job_manager.h).
#ifndef INTERSLICE_SERVER_ENGINE_ARTIFACTS_H_
#define INTERSLICE_SERVER_ENGINE_ARTIFACTS_H_

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/pipeline/pipeline.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::server {

// Every file of every artifact, in report order (a derived DICOM series is a
// folder: each of its files becomes an artifact named "<folder>/<file>", one
// level, the only nesting), with its size and SHA-256 hashed on `threads`
// threads; `total_bytes` their sum.
absl::StatusOr<std::vector<v1::ArtifactInfo>> DescribeArtifacts(
    const std::vector<Artifact>& produced, int threads, int64_t* total_bytes);

// The files of a job's DICOM artifacts (media type application/dicom),
// in artifact order, below its output folder: what its deliveries send.
template <typename Artifacts>
std::vector<std::string> DicomArtifactFiles(const Artifacts& artifacts,
                                            const std::string& output_dir) {
  std::vector<std::string> files;
  for (const v1::ArtifactInfo& a : artifacts) {
    if (a.media_type() == "application/dicom") {
      files.push_back((std::filesystem::path(output_dir) / a.name()).string());
    }
  }
  return files;
}

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_ENGINE_ARTIFACTS_H_
