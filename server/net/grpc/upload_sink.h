// The disk side of an upload on the Interpolate and Submit streams
// (service_upload.cc): the reactors post each message to the I/O executor,
// which hands it to an UploadSink.
#ifndef INTERSLICE_SERVER_NET_GRPC_UPLOAD_SINK_H_
#define INTERSLICE_SERVER_NET_GRPC_UPLOAD_SINK_H_

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "interslice/v1/interslice.pb.h"
#include "job/job.h"
#include "server/base/metrics.h"
#include "server/engine/job_manager.h"
#include "server/engine/spool.h"
#include "server/net/grpc/upload_stream.h"

namespace interslice::server {

// Receives one upload (header, then the files' chunks) into the spool, as
// UploadStream directs. Blocking: called on the I/O executor only, one call
// at a time per upload.
class UploadSink {
 public:
  UploadSink(JobManager* manager, Spool* spool, Metrics* metrics,
             const UploadStreamLimits& limits, bool ephemeral,
             std::optional<std::chrono::steady_clock::time_point> deadline,
             std::string owner)
      : manager_(manager),
        spool_(spool),
        metrics_(metrics),
        stream_(limits),
        ephemeral_(ephemeral),
        deadline_(deadline),
        owner_(std::move(owner)) {}
  ~UploadSink() { CloseFile(); }

  absl::Status Consume(const v1::UploadRequest& message);

  // The client half-closed: the upload must be complete.
  absl::Status Finish();

  // Deletes whatever was received unless the job was queued. Idempotent.
  void Abort();

  const std::shared_ptr<Job>& job() const { return job_; }
  bool enqueued() const { return enqueued_; }

 private:
  static void FsyncDir(const std::string& dir);

  absl::Status OpenFile(int index, const std::string& client_name);
  absl::Status Write(int64_t offset, std::string_view data);
  absl::Status SyncAndCloseFile();
  void CloseFile();

  JobManager* const manager_;
  Spool* const spool_;
  Metrics* const metrics_;
  UploadStream stream_;
  // The uploads the job's kind takes by name, and which of them arrived.
  std::vector<job::NamedUpload> named_;
  std::vector<bool> received_;
  const bool ephemeral_;
  const std::optional<std::chrono::steady_clock::time_point> deadline_;
  const std::string owner_;
  std::shared_ptr<Job> job_;
  int fd_ = -1;
  bool enqueued_ = false;
  bool aborted_ = false;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_UPLOAD_SINK_H_
