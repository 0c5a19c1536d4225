// A job's results on the client's disk, as `interpolate` (and `fill
// --server`, in one call) and `fetch` receive them: artifact files checked
// against the server's size and SHA-256, the report with local paths, the
// region line of the summary.
#ifndef INTERSLICE_CLIENT_REMOTE_ARTIFACTS_H_
#define INTERSLICE_CLIENT_REMOTE_ARTIFACTS_H_

#include <cstdint>
#include <fstream>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "core/common/sha256.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::client::remote {

// SHA-256 of a file, raw bytes; empty when it cannot be read (the upload
// of that file then fails on its own).
std::string HashFile(const std::string& path);

// Writes one artifact to <dir>/<name>.part, then checks its size and
// SHA-256 and renames it to <dir>/<name>. Begin refuses a name that
// IsSafeArtifactName (client/remote_commands.h) refuses.
class ArtifactFile {
 public:
  // Starts the file; with `offset` > 0 appends to the part an earlier,
  // interrupted download left (its first `offset` bytes).
  absl::Status Begin(const std::string& dir, const v1::ArtifactInfo& info,
                     int64_t offset);
  absl::Status Append(const std::string& data);
  absl::Status Commit();
  bool open() const { return out_.is_open(); }
  const std::string& part_path() const { return part_; }

 private:
  v1::ArtifactInfo info_;
  std::string final_, part_;
  std::ofstream out_;
  std::unique_ptr<Sha256> hash_;
  int64_t bytes_ = 0;
};

// Whether `path` already holds the artifact: a regular file of its size and
// SHA-256.
bool IsCompleteArtifact(const std::string& path, const v1::ArtifactInfo& info);

// The server's report with artifact paths turned into local ones.
absl::Status WriteReport(const std::string& report_json,
                         const std::string& out_dir, const std::string& path);

// The region of interest an interpolation job used, as the in-process
// summary says it (a fill's report has none: nothing is printed).
void PrintRegion(const std::string& report_json);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_ARTIFACTS_H_
