// The DICOM listener: a Storage SCP on DCMTK's SCP pool (DcmBaseSCPPool with
// a DcmThreadSCP worker per association; no PDU code of our own).
//
// Services: Verification (C-ECHO) and Storage (C-STORE) of CT Image, Enhanced
// CT Image, Legacy Converted Enhanced CT Image, MR Image, Enhanced MR Image
// and Legacy Converted Enhanced MR Image. Storage presentation contexts
// accept exactly the transfer syntaxes core's reader decodes
// (DecodableTransferSyntaxes()); a context proposing none of them, or an
// abstract syntax not listed, is refused in negotiation.
//
// Association policy: the called AE title must be one of options.ae_titles;
// the calling AE title must be a peer's (unless accept_unknown_callers).
// Otherwise the association is rejected (A-ASSOCIATE-RJ). At most
// max_associations at once (more: rejected, "local limit exceeded").
// Timeouts: ACSE (association set-up and release) and DIMSE (waiting for the
// next message or data) bound how long a silent peer holds its worker.
//
// C-STORE: the data set streams into a file in the spool, which the
// SeriesAssembler fsyncs and renames into its series before the response
// leaves: success means kept. Spool quota or per-series limits reached:
// 0xA700 (Refused: out of resources) and the file is deleted. Not DICOM /
// no UIDs: 0xC000 (Error: cannot understand). A data set that grows past the
// per-series byte limit while it streams in is cut off by aborting the
// association (the peer loses that association only).
//
// DCMTK 3.6.7's SCP pool listens on every interface; the HOST part of
// --dicom-listen is checked but only loopback/any are meaningful (see
// docs/dicom-node.md).
#ifndef INTERSLICE_SERVER_DICOM_STORAGE_SCP_H_
#define INTERSLICE_SERVER_DICOM_STORAGE_SCP_H_

#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "server/dicom/config.h"
#include "server/dicom/peer.h"

namespace interslice::server {
class Metrics;
}  // namespace interslice::server

namespace interslice::server::dicom {

class SeriesAssembler;

struct StorageScpOptions {
  int port = 0;  // 0: a free port is chosen (see StorageScp::port())
  std::vector<std::string> ae_titles = {"INTERSLICE"};
  PeersConfig peers;
  int max_associations = 8;
  uint32_t max_pdu_bytes = 65536;  // what we announce to receive
  double acse_timeout_seconds = 10;
  double dimse_timeout_seconds = 60;
  // All three set: TLS (server/dicom/tls.h), peers must present a
  // certificate a listed CA signed. All empty: plain TCP.
  DicomTlsFiles tls;
};

class StorageScp {
 public:
  // Binds the port and starts listening on a thread of its own. `assembler`
  // and `metrics` (may be null) must outlive the listener.
  static absl::StatusOr<std::unique_ptr<StorageScp>> Start(
      const StorageScpOptions& options, SeriesAssembler* assembler,
      Metrics* metrics);
  ~StorageScp();  // Stop()

  int port() const { return port_; }
  // Stops accepting associations and waits (bounded by the DIMSE timeout)
  // for those in progress to end.
  void Stop();

  struct Impl;

 private:
  StorageScp() = default;
  std::unique_ptr<Impl> impl_;
  int port_ = 0;
};

// The storage SOP classes offered (UIDs), in the order offered.
std::vector<std::string> AcceptedStorageSopClasses();

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_STORAGE_SCP_H_
