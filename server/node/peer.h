// The DICOM peers the server talks to (a PACS, a modality, a
// workstation, a DICOMweb service), as listed in the peers file
// (--dicom-peers; server/node/config.h has the file format), and the one
// interface every door and the engine use to talk to them: PeerClient
// (Echo, Find, Retrieve, Store). Its implementations live in the protocol
// folders above the node (server/net/dimse/dimse_peer.h for DIMSE,
// server/net/dicomweb/dicomweb_peer.h for DICOMweb); the app builds them
// through a PeerClientFactory, the only place that looks at a peer's type
// to choose a protocol. The peer registry (peer_registry.h) holds them.
//
// Plain data and an interface: no DCMTK, curl or gRPC types here.
#ifndef INTERSLICE_SERVER_NODE_PEER_H_
#define INTERSLICE_SERVER_NODE_PEER_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"

namespace interslice::server::node {

// TLS material for DICOM associations (DICOM PS3.15 Annex B, BCP 195
// profile). Empty paths mean "no TLS".
struct DicomTlsFiles {
  std::string certificate;      // PEM: our certificate
  std::string private_key;      // PEM: its key (unencrypted)
  std::string ca_certificates;  // PEM: CAs that sign peer certificates
};

// An address range: the first `prefix_bits` bits of `address` (IPv4 in the
// first 4 bytes, family 4; IPv6, family 6), as "10.1.0.0/16" or "::1".
struct SourceNetwork {
  int family = 4;
  unsigned char address[16] = {};
  int prefix_bits = 32;
  std::string text;  // as written, for messages
};

// How we talk to a peer: DIMSE associations (C-STORE, C-GET, C-FIND,
// C-ECHO), or DICOMweb over HTTP(S) (STOW-RS, QIDO-RS, WADO-RS; PS3.18).
enum class PeerType { kDimse, kDicomWeb };

// How a series is pulled from a DIMSE peer (JobSpec.pacs_source): C-GET
// (the instances come back on our association), or C-MOVE with the
// server's own DICOM listener as the move destination (the peer opens
// associations to our first AE title; it must know that AE title, and the
// server must run its listener).
enum class RetrieveMethod { kGet, kMove };

// A DICOMweb peer's address and credentials. Paths, never secrets: the
// secret files are read when a request is made (so a rotated token is
// picked up without a restart), and their contents are never logged.
struct DicomWebEndpoint {
  // The service's base URL, http:// or https://, without credentials,
  // query or trailing slash ("http://pacs:8042/dicom-web"); requests go to
  // {url}/studies... (PS3.18 8.2 resource paths).
  std::string url;
  // At most one of: a bearer token (the file's text, trimmed, RFC 6750),
  // HTTP basic (user and the password file's text, trimmed, RFC 7617).
  std::string bearer_token_file;
  std::string basic_user;
  std::string basic_password_file;
  // Mutual TLS: our certificate and its unencrypted key (PEM), https only.
  std::string client_certificate;
  std::string client_key;
  // PEM CAs that sign the server's certificate (https; empty: the system's).
  std::string ca_certificates;
};

struct DicomPeer {
  std::string name;  // how rules and clients refer to it ("orthanc")
  PeerType type = PeerType::kDimse;
  // DICOMweb peers (type kDicomWeb) only; the DIMSE fields below (AE title,
  // host, port, tls, allowed_sources) are empty/default for them.
  DicomWebEndpoint web;
  std::string ae_title;  // 1-16 characters, no backslash
  std::string host;
  int port = 104;
  bool tls = false;  // associations with this peer use TLS
  // Deliveries to this peer send over up to this many associations at once
  // (1-16; 1: one after another). DIMSE waits for each C-STORE response, so
  // parallel associations keep a PACS's storage busy while we wait. For a
  // DICOMweb peer: STOW-RS requests in flight at once.
  int max_associations = 4;
  // DIMSE peers only (peers-file key `retrieve: get|move`).
  RetrieveMethod retrieve = RetrieveMethod::kGet;
  // Associations calling as this peer's AE title are accepted only from
  // these addresses (empty: from anywhere).
  std::vector<SourceNetwork> allowed_sources;
};

// "peer NAME (AE@HOST:PORT)", or "peer NAME (URL)" for a DICOMweb peer, for
// errors and logs (no patient data, no credentials: a DICOMweb URL never
// holds any, the peers file refuses them).
std::string PeerLabel(const DicomPeer& peer);

// ---- Find: what a peer holds (C-FIND, or QIDO-RS) -------------------------
// Keys (DICOM PS3.4 C.2.2.2 matching, done by the peer): patient_id,
// accession_number single values (wildcards * and ? allowed), study_date a
// date or range ("20240101", "20240101-20240131", "-20240131"); modality
// filters both the study (ModalitiesInStudy) and its series. Empty keys
// match everything.
struct FindQuery {
  std::string patient_id;
  std::string study_date;
  std::string modality;
  std::string accession_number;
};

struct FoundSeries {
  std::string series_instance_uid;
  std::string modality;
  std::string series_number;
  std::string series_description;
  // NumberOfSeriesRelatedInstances when the peer gives it, else -1.
  int64_t instances = -1;
};

struct FoundStudy {
  std::string study_instance_uid;
  std::string patient_id;
  std::string study_date;
  std::string accession_number;
  std::string study_description;
  std::string modalities;  // ModalitiesInStudy, as the peer writes it
  std::vector<FoundSeries> series;
};

struct FindResult {
  std::vector<FoundStudy> studies;
  // More studies or series matched than the caps allowed.
  bool truncated = false;
};

// At most this many studies, and series in all; what a peer lists beyond
// them is dropped (FindResult::truncated).
struct FindLimits {
  int max_studies = 100;
  int max_series = 1000;
};

// Keys are checked before anything is sent: a backslash (a value list), a
// control character, a value longer than its VR allows (LO 64, SH 16, CS
// 16) or a malformed date is INVALID_ARGUMENT naming the key.
absl::Status CheckFindQuery(const FindQuery& query);

// ---- Retrieve: a series a peer holds, into a folder -----------------------
struct RetrieveLimits {
  // More instances or bytes in all end the retrieval (RESOURCE_EXHAUSTED).
  int64_t max_instances = 100000;
  int64_t max_bytes = int64_t{2} << 30;
  // A C-MOVE waits for another job's move of the same series from the same
  // peer to end, at most this long (then FAILED_PRECONDITION) and only
  // while `cancel` (the job's; may be null) is not cancelled.
  int move_wait_seconds = 3600;
  const CancellationToken* cancel = nullptr;
};

struct RetrieveResult {
  int64_t instances = 0;
  int64_t bytes = 0;
};

// ---- Store: files onto a peer (C-STORE, or STOW-RS) -----------------------
struct StoreResult {
  int accepted = 0;
  int refused = 0;
  // The peer's status text for the first refused instance; empty if none.
  std::string first_refusal;
};

// How this server talks to every peer: as whom, with which TLS files, and
// how long each kind of exchange may take (connect, associate, each
// message or each idle stretch of a transfer).
struct PeerClientSettings {
  // Our AE title on outgoing associations (the first --dicom-ae).
  std::string calling_ae_title = "INTERSLICE";
  // Our certificate, key and CA for DIMSE peers with tls: true.
  DicomTlsFiles tls;
  uint32_t max_pdu_bytes = 65536;
  // Short: a check of several dead peers stays quick.
  int echo_timeout_seconds = 5;
  int find_timeout_seconds = 30;
  int retrieve_timeout_seconds = 60;
  int store_timeout_seconds = 30;
  // DICOMweb peers: one STOW-RS request carries at most this many instances
  // and bytes (a larger file goes alone), so that a proxy's body limit or a
  // peer's per-request memory is not exceeded and parallel requests share
  // the work.
  int stow_max_instances = 50;
  int64_t stow_max_bytes = int64_t{64} << 20;
};

// How a peer is shown to an operator (status page): never credentials.
struct PeerSummary {
  std::string name;
  std::string ae_title;  // "(DICOMweb)" for a DICOMweb peer
  std::string address;   // HOST:PORT, or the base URL
  bool tls = false;
};

// One peer, spoken to in its own protocol. Every call blocks for up to the
// settings' timeouts: call it from a worker thread, never from a gRPC
// reactor. Errors are one line naming the peer (PeerLabel), never a UID or
// a query key's value, with the same codes whatever the protocol:
// UNAVAILABLE (cannot be reached, refuses us, stops answering; worth a
// retry), PERMISSION_DENIED (refused credentials), FAILED_PRECONDITION (the
// peer does not offer the service, or answers with a failure status),
// NOT_FOUND (nothing matches), RESOURCE_EXHAUSTED (over a limit),
// INVALID_ARGUMENT (a bad key or file of ours, or a malformed answer).
class PeerClient {
 public:
  explicit PeerClient(DicomPeer peer) : peer_(std::move(peer)) {}
  virtual ~PeerClient() = default;
  PeerClient(const PeerClient&) = delete;
  PeerClient& operator=(const PeerClient&) = delete;

  const DicomPeer& peer() const { return peer_; }
  const std::string& name() const { return peer_.name; }

  // Is the peer there and does it take us (C-ECHO; a QIDO-RS search for a
  // DICOMweb peer). OK, or the codes above.
  virtual absl::Status Echo() = 0;
  // What Echo does, for logs: "a C-ECHO", "a QIDO-RS probe".
  virtual std::string EchoName() const = 0;
  // Echo's success in words for `--check-config`: "C-ECHO answered (calling
  // as INTERSLICE)", "QIDO-RS answered".
  virtual std::string EchoAnswered() const = 0;

  // A STUDY-level search with the keys, then the series of each study
  // found, within `limits`. The query is checked first (CheckFindQuery).
  virtual absl::StatusOr<FindResult> Find(const FindQuery& query,
                                          const FindLimits& limits) = 0;

  // Every instance of the series into `dest_dir` (which must exist), each
  // written as a Part 10 file, checked by the bounded scan
  // (dataset_scan.h), fsynced and renamed as it arrives, the folder fsynced
  // at the end: a job later reads only complete, well-formed files. A
  // partial retrieval is an error, and on every error the files received
  // so far are removed.
  virtual absl::StatusOr<RetrieveResult> Retrieve(
      const std::string& study_instance_uid,
      const std::string& series_instance_uid, const std::string& dest_dir,
      const RetrieveLimits& limits) = 0;

  // The files stored on the peer, over up to peer().max_associations
  // associations (or requests) at once. Returns how many the peer accepted
  // and, for the first refusal, its status; an error when the peer cannot
  // be reached (UNAVAILABLE) or a file cannot be read (INVALID_ARGUMENT).
  // Never retries by itself (the outbox does).
  virtual absl::StatusOr<StoreResult> Store(
      const std::vector<std::string>& files) = 0;

  // For the status page.
  virtual PeerSummary Summary() const = 0;

 private:
  const DicomPeer peer_;
};

// Makes the client of one peer: the app's choice of protocol by the peer's
// type (server/app/). Never null.
using PeerClientFactory =
    std::function<std::unique_ptr<PeerClient>(const DicomPeer& peer)>;

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_PEER_H_
