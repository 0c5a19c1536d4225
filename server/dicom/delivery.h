// Storing a job's DICOM results on DICOM peers (Storage SCU, DCMTK
// DcmStorageSCU), persistently: the outbox.
//
// Contract:
// - StoreFiles sends DICOM files to one peer: a DICOMweb peer by STOW-RS
//   (server/dicomweb/client.h, StowFiles: requests instead of
//   associations, the same counts and error codes); a DIMSE peer as
//   follows. The files are dealt
//   round-robin into min(peer.max_associations, files) shares sent at once,
//   each by a DcmStorageSCU of its own over as many associations as it
//   needs (it proposes each file's SOP class with its own transfer syntax,
//   plus the uncompressed ones, and splits at 128 presentation contexts):
//   so never more than max_associations associations with the peer at a
//   time (the queue runs one delivery at a time). A share that fails fails
//   the call (the queue's retry sends every file again); the counts are the
//   sums of the shares'. It returns how many instances the peer accepted
//   (DIMSE success or warning) and, for the first refusal, the peer's status
//   ("0xA700 Refused: Out of resources"). A peer that cannot be reached or
//   rejects the association is UNAVAILABLE naming the peer; files that
//   cannot be read are INVALID_ARGUMENT. Never retries by itself.
// - DeliveryQueue is the outbox: Add() registers a delivery (job, peer,
//   files). A single thread of its own (never a gRPC thread) tries each due
//   delivery; a failed try is retried after a backoff that doubles from
//   initial_backoff up to max_backoff, until the peer accepts every
//   instance (DELIVERED) or give_up_after has passed since the delivery was
//   first added (FAILED, with the last error). Every change is reported
//   through `on_update` (the job manager stores it in the job's status and
//   spool record, which is what makes deliveries survive a restart: at
//   start-up the manager Add()s the PENDING ones again, keeping their
//   attempts and next attempt time). A try is reported (attempts + 1, still
//   PENDING) before it is made, so that a kill during it still counts it.
// - Sending again is harmless: the derived objects have fixed SOP Instance
//   UIDs, so a PACS replaces (or ignores) the copy.
// - Metrics: instances sent and failed per peer name (no UIDs). Logs name
//   the job id, the peer name and counts, never patient data or UIDs.
#ifndef INTERSLICE_SERVER_DICOM_DELIVERY_H_
#define INTERSLICE_SERVER_DICOM_DELIVERY_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.pb.h"
#include "server/dicom/peer.h"

namespace interslice::server::dicom {

struct DeliveryOptions {
  // Our AE title on outgoing associations.
  std::string calling_ae_title = "INTERSLICE";
  std::chrono::milliseconds initial_backoff{2000};
  std::chrono::milliseconds max_backoff{5 * 60 * 1000};
  // After this long without success a delivery is FAILED (its results then
  // expire with the job's retention).
  std::chrono::milliseconds give_up_after{24 * 3600 * 1000};
  // TCP connect, association and DIMSE timeouts.
  int timeout_seconds = 30;
  uint32_t max_pdu_bytes = 65536;
  // Our certificate, key and CA for peers with tls: true.
  DicomTlsFiles tls;
  // DICOMweb peers: one STOW-RS request carries at most this many instances
  // and bytes (a larger file goes alone), so that a proxy's body limit or a
  // peer's per-request memory is not exceeded and parallel requests share
  // the work (server/dicomweb/client.h).
  int stow_max_instances = 50;
  int64_t stow_max_bytes = int64_t{64} << 20;
};

struct StoreResult {
  int accepted = 0;
  int refused = 0;
  // The peer's status text for the first refused instance; empty if none.
  std::string first_refusal;
};

absl::StatusOr<StoreResult> StoreFiles(const DicomPeer& peer,
                                       const std::vector<std::string>& files,
                                       const DeliveryOptions& options);

// Every DICOM file (Part 10, "DICM" at offset 128) under `dir`, sorted.
std::vector<std::string> ListDicomFiles(const std::string& dir);

// Counters for the outbox (the server's Metrics implements them).
struct DeliveryCounters {
  std::function<void(const std::string& peer, int n)> sent;
  std::function<void(const std::string& peer, int n)> failed;
};

class DeliveryQueue {
 public:
  using OnUpdate =
      std::function<void(const std::string& job_id, const v1::Delivery&)>;

  DeliveryQueue(std::vector<DicomPeer> peers, DeliveryOptions options,
                OnUpdate on_update, DeliveryCounters counters = {});
  ~DeliveryQueue();  // Stop()
  DeliveryQueue(const DeliveryQueue&) = delete;
  DeliveryQueue& operator=(const DeliveryQueue&) = delete;

  void Start();
  // Stops the thread after the try in progress (which ends by the timeouts).
  void Stop();

  // The configured peers and options (the retriever uses them too).
  std::optional<DicomPeer> FindPeer(const std::string& name) const;
  const DeliveryOptions& options() const { return options_; }

  // INVALID_ARGUMENT naming the first name that is not a configured peer.
  absl::Status CheckPeers(const std::vector<std::string>& names) const;

  // Registers the delivery of `files` to `state.peer` for `job_id`. `state`
  // is the delivery as last persisted (a new one: PENDING, attempts 0);
  // `first_added_unix_ms` is when it was first registered (for
  // give_up_after). DELIVERED or FAILED ones are ignored.
  void Add(const std::string& job_id, v1::Delivery state,
           std::vector<std::string> files, int64_t first_added_unix_ms);
  // Forgets every delivery of `job_id` (its results are being deleted).
  void Forget(const std::string& job_id);

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

  const std::vector<DicomPeer> peers_;
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

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_DELIVERY_H_
