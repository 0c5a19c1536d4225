// The outbox: a job's DICOM results stored on DICOM peers, persistently.
//
// Contract:
// - DeliveryQueue is the engine's ResultOutbox (engine/peer_services.h):
//   Add() registers a delivery (job, peer, files). A single thread of its
//   own (never a gRPC thread) tries each due delivery through the peer's
//   client (PeerClient::Store, server/node/peer.h: C-STORE or STOW-RS; one
//   delivery at a time, each over up to the peer's max_associations); a
//   failed try is retried after a backoff that doubles from initial_backoff
//   up to max_backoff, until the peer accepts every instance (DELIVERED) or
//   give_up_after has passed since the delivery was first added (FAILED,
//   with the last error). Every change is reported through `on_update` (the
//   job manager stores it in the job's status and spool record, which is
//   what makes deliveries survive a restart: at start-up the manager Add()s
//   the PENDING ones again, keeping their attempts and next attempt time).
//   A try is reported (attempts + 1, still PENDING) before it is made, so
//   that a kill during it still counts it.
// - Each try asks the peer registry for the peer's client then: after a
//   reload (SIGHUP) the next try goes to the peer's new address; a peer that
//   was removed fails the try (FAILED_PRECONDITION) and is retried, as a
//   peer that cannot be reached is.
// - Sending again is harmless: the derived objects have fixed SOP Instance
//   UIDs, so a PACS replaces (or ignores) the copy.
// - Metrics: instances sent and failed per peer name (no UIDs). Logs name
//   the job id, the peer name and counts, never patient data or UIDs.
#ifndef INTERSLICE_SERVER_NODE_OUTBOX_H_
#define INTERSLICE_SERVER_NODE_OUTBOX_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.pb.h"
#include "server/engine/peer_services.h"
#include "server/node/peer.h"
#include "server/node/peer_registry.h"

namespace interslice::server::node {

struct DeliveryOptions {
  std::chrono::milliseconds initial_backoff{2000};
  std::chrono::milliseconds max_backoff{5 * 60 * 1000};
  // After this long without success a delivery is FAILED (its results then
  // expire with the job's retention).
  std::chrono::milliseconds give_up_after{24 * 3600 * 1000};
};

// Every DICOM file (Part 10, "DICM" at offset 128) under `dir`, sorted.
std::vector<std::string> ListDicomFiles(const std::string& dir);

// Counters for the outbox (the server's Metrics implements them).
struct DeliveryCounters {
  std::function<void(const std::string& peer, int n)> sent;
  std::function<void(const std::string& peer, int n)> failed;
};

class DeliveryQueue : public ResultOutbox {
 public:
  using OnUpdate =
      std::function<void(const std::string& job_id, const v1::Delivery&)>;

  // `peers` must outlive the queue.
  DeliveryQueue(const PeerRegistry* peers, DeliveryOptions options,
                OnUpdate on_update, DeliveryCounters counters = {});
  ~DeliveryQueue() override;  // Stop()
  DeliveryQueue(const DeliveryQueue&) = delete;
  DeliveryQueue& operator=(const DeliveryQueue&) = delete;

  void Start();
  // Stops the thread after the try in progress (which ends by the timeouts).
  void Stop();

  // ResultOutbox (engine/peer_services.h).
  absl::Status CheckPeers(const std::vector<std::string>& names) const override;
  void Add(const std::string& job_id, v1::Delivery state,
           std::vector<std::string> files,
           int64_t first_added_unix_ms) override;
  void Forget(const std::string& job_id) override;

  // Deliveries not finished yet (PENDING), for tests and gauges.
  int pending();

 private:
  struct Entry {
    std::string job_id;
    v1::Delivery state;
    std::vector<std::string> files;
    int64_t first_added_unix_ms = 0;
  };
  void Loop();
  void Try(Entry& entry);

  const PeerRegistry* const peers_;
  const DeliveryOptions options_;
  const OnUpdate on_update_;
  const DeliveryCounters counters_;

  std::mutex mu_;
  std::condition_variable cv_;
  // (job id, peer name) -> entry.
  std::map<std::pair<std::string, std::string>, Entry> entries_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_OUTBOX_H_
