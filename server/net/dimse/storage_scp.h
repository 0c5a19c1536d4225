// The DICOM listener: a Storage SCP. The gate (connection_gate.h) owns the
// listening socket and every connection until its association request has
// arrived; a fixed pool of association workers then runs DCMTK's association
// state machine (association.h) on it.
//
// Services: Verification (C-ECHO) and Storage (C-STORE) of CT Image, Enhanced
// CT Image, Legacy Converted Enhanced CT Image, MR Image, Enhanced MR Image,
// Legacy Converted Enhanced MR Image, Segmentation and RT Structure Set.
// Storage presentation contexts accept exactly the transfer syntaxes core's
// reader decodes (DecodableTransferSyntaxes()); a context proposing none of
// them, or an abstract syntax not listed, is refused in negotiation.
//
// Association policy (association.h): called AE title one of
// options.ae_titles; calling AE title a peer's (unless
// accept_unknown_callers), from the peer's allowed_sources when it lists
// any. At most max_associations at once, at most
// max_associations_per_source from one address (more: A-ASSOCIATE-RJ,
// "local limit exceeded").
//
// Timeouts: the association request must arrive whole within
// acse_timeout_seconds of the connection; within an association each PDU
// within pdu_timeout_seconds of its first byte, and DCMTK waits at most
// dimse_timeout_seconds for the next message.
//
// C-STORE: see association.h (success means kept: fsynced in the spool).
#ifndef INTERSLICE_SERVER_NET_DIMSE_STORAGE_SCP_H_
#define INTERSLICE_SERVER_NET_DIMSE_STORAGE_SCP_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/config.h"
#include "server/node/peer.h"

namespace interslice::server {
class AuditLog;
class Metrics;
namespace node {
class Intake;
}  // namespace node
}  // namespace interslice::server

namespace interslice::server::dimse {

class PendingMoves;

struct StorageScpOptions {
  // The address to listen on, exactly: a numeric IPv4 or IPv6 address, ""
  // or "*" (every IPv4 interface), "::" (every interface).
  std::string host = "127.0.0.1";
  int port = 0;  // 0: a free port is chosen (see StorageScp::port())
  std::vector<std::string> ae_titles = {"INTERSLICE"};
  node::PeersConfig peers;
  int max_associations = 8;
  // 0: half of max_associations, at least 1.
  int max_associations_per_source = 0;
  // Connections waiting for their association request, in all and from one
  // address (beyond: the oldest waiting one is closed).
  int max_pending = 64;
  int max_pending_per_source = 16;
  uint32_t max_pdu_bytes = 65536;  // what we announce to receive
  double acse_timeout_seconds = 10;
  double dimse_timeout_seconds = 60;
  double pdu_timeout_seconds = 30;
  // All three set: TLS (server/net/dimse/tls.h), peers must present a
  // certificate a listed CA signed. All empty: plain TCP.
  node::DicomTlsFiles tls;
  // Associations accepted, ended and refused are recorded here (may be
  // null: no audit trail). Outlives the listener.
  AuditLog* audit = nullptr;
  // The C-MOVEs of ours in progress (pending_moves.h): instances that
  // belong to one go to its folder instead of the assembler. May be null
  // (no moves). Outlives the listener.
  PendingMoves* pending_moves = nullptr;
};

class StorageScp {
 public:
  // Binds the address and starts the gate and the association workers.
  // `assembler` and `metrics` (may be null) must outlive the listener.
  // UNAVAILABLE with one line when the address cannot be bound (in use, not
  // this host's); INVALID_ARGUMENT for bad options.
  static absl::StatusOr<std::unique_ptr<StorageScp>> Start(
      const StorageScpOptions& options, node::Intake* intake, Metrics* metrics);
  ~StorageScp();  // Stop()

  int port() const;
  // Replaces the peers file's content (a reload on SIGHUP): associations
  // requested from now on are checked against it.
  void SetPeers(node::PeersConfig peers);
  // Stops accepting connections (waiting ones are closed) and waits for the
  // associations in progress to end (bounded by the timeouts).
  void Stop();

  struct Impl;

 private:
  StorageScp() = default;
  std::unique_ptr<Impl> impl_;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_STORAGE_SCP_H_
