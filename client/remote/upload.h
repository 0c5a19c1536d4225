// Uploading a job: the files found under the inputs, the stream that sends
// them after the job's header, and the two calls that take an upload: one
// Interpolate call (`interpolate`, `fill --server`) and Submit (`submit`,
// `fill --server --submit`).
#ifndef INTERSLICE_CLIENT_REMOTE_UPLOAD_H_
#define INTERSLICE_CLIENT_REMOTE_UPLOAD_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client/grpc_channel.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::client::remote {

struct LocalFile {
  std::string path;
  std::string name;
  int64_t size = 0;
};

// Every regular file under the inputs, found as `interslice run` finds them
// (core/dicom CollectInputFiles: recursive, de-duplicated, sorted; the
// server skips what is not DICOM), so that a remote job reads the same
// files as the local one. Uploaded under their own file names (the server
// stores them by index).
absl::StatusOr<std::vector<LocalFile>> CollectFiles(
    const std::vector<std::string>& inputs);

// One Interpolate call: uploads `files` after `header`, writes the artifacts
// to `out` and the report to `report` (if not empty).
int InterpolateCall(const Connection& connection,
                    const v1::UploadHeader& header,
                    const std::vector<LocalFile>& files, const std::string& out,
                    const std::string& report, bool quiet,
                    double deadline_seconds);

// A detached job: uploads `files` after `header` by Submit and prints the
// job's id (the one line on stdout, for scripts).
int SubmitCall(const Connection& connection, const v1::UploadHeader& header,
               const std::vector<LocalFile>& files);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_UPLOAD_H_
