// What the engine asks of the DICOM node, which lives above it
// (server/node/): a series pulled from a peer before a job runs
// (JobSpec.pacs_source), and the outbox a job's DICOM results go to
// (JobSpec.send_to). The node implements both (node/peer_registry.h,
// node/outbox.h); the app hands them to the job manager. Without them the
// server has no DICOM peers, and jobs that name one are refused.
#ifndef INTERSLICE_SERVER_ENGINE_PEER_SERVICES_H_
#define INTERSLICE_SERVER_ENGINE_PEER_SERVICES_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::server {

// A series that was retrieved into a job's folder.
struct RetrievedSeries {
  int64_t instances = 0;
  int64_t bytes = 0;
};

class PeerSeriesSource {
 public:
  virtual ~PeerSeriesSource() = default;
  // INVALID_ARGUMENT when `name` is not a configured peer.
  virtual absl::Status CheckPeer(const std::string& name) const = 0;
  // Blocking: every instance of the series `source` names into `dest_dir`
  // (which exists and is empty), each complete, well-formed and fsynced
  // before it is kept, at most `max_bytes` in all; on error nothing of it
  // is left. FAILED_PRECONDITION when the peer is no longer configured;
  // otherwise the peer's own errors (server/node/peer.h, PeerClient).
  virtual absl::StatusOr<RetrievedSeries> Retrieve(
      const v1::PacsSeriesSource& source, const std::string& dest_dir,
      int64_t max_bytes, const CancellationToken* cancel) = 0;
};

class ResultOutbox {
 public:
  virtual ~ResultOutbox() = default;
  // INVALID_ARGUMENT naming the first name that is not a configured peer.
  virtual absl::Status CheckPeers(
      const std::vector<std::string>& names) const = 0;
  // Registers the delivery of `files` (a job's DICOM results) to
  // `state.peer` for `job_id`. `state` is the delivery as last persisted (a
  // new one: PENDING, attempts 0); `first_added_unix_ms` is when it was
  // first registered. DELIVERED or FAILED ones are ignored. Every change of
  // its state comes back through JobManager::UpdateDelivery.
  virtual void Add(const std::string& job_id, v1::Delivery state,
                   std::vector<std::string> files,
                   int64_t first_added_unix_ms) = 0;
  // Forgets every delivery of `job_id` (its results are being deleted).
  virtual void Forget(const std::string& job_id) = 0;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_ENGINE_PEER_SERVICES_H_
