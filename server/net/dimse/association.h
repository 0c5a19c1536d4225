// One association of the DICOM listener, on a connection the gate handed
// over (connection_gate.h): DCMTK's association state machine (DcmThreadSCP)
// behind a transport connection of ours that replays the bytes the gate
// already read and passes every byte through the connection's PduGuard
// before DCMTK sees it (pdu_guard.h).
//
// DCMTK 3.6.7 takes an already accepted socket only through a process-wide
// setting made for inetd (dcmExternalSocketHandle): it is set, under a
// mutex, just before DCMTK receives the association and reset by our
// transport layer as DCMTK creates the connection, before it reads a byte;
// so associations start one at a time but run in parallel.
//
// Policy (the calls DCMTK makes back): the called AE title must be one of
// options.ae_titles; the calling AE title must be a peer's (unless
// accept_unknown_callers), from one of that peer's allowed_sources when it
// lists any. Every rejection (A-ASSOCIATE-RJ) is counted in
// associations_rejected and by reason (RefusalLog), C-FIND/C-MOVE/C-GET
// proposals included (they are refused in negotiation: no presentation
// context).
//
// C-STORE: the data set is written to a staging file as it arrives, bit for
// bit (DCMTK does not parse it). When the caller has a C-MOVE of ours
// pending (options.pending_moves, pending_moves.h), the file is scanned and
// its UIDs read first: an instance of the move goes to the move's folder
// (never to the assembler or the rules). Otherwise
// the node's intake (server/node/intake.h, AddInstance) scans and takes it; the
// response says what happened: success; 0xA700 (out of resources: limits,
// quota, disk full — the association goes on); 0xC000 (cannot understand: not
// well-formed within the scan's limits, no UIDs); 0xA900 (data set does not
// match SOP class). An instance that grows past the per-series byte limit while
// it streams in is cut off by aborting the association.
#ifndef INTERSLICE_SERVER_NET_DIMSE_ASSOCIATION_H_
#define INTERSLICE_SERVER_NET_DIMSE_ASSOCIATION_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "server/net/dimse/connection_gate.h"
#include "server/net/dimse/storage_scp.h"

namespace interslice::server {
class Metrics;
namespace node {
class Intake;
}  // namespace node
}  // namespace interslice::server

namespace interslice::server::dimse {

class AssociationRunner {
 public:
  // `assembler`, `metrics` (may be null), `refusals` and `gate` (may be
  // null: no deadlines, as in the fuzzer) must outlive the runner.
  static absl::StatusOr<std::unique_ptr<AssociationRunner>> Create(
      const StorageScpOptions& options, node::Intake* intake, Metrics* metrics,
      RefusalLog* refusals, ConnectionGate* gate);
  ~AssociationRunner();

  // Blocking, on the calling thread: the whole association on `connection`
  // (its socket is closed at the end).
  void Serve(ReadyConnection connection);
  // Replaces the peers whose calling AE titles are accepted (a reload);
  // associations already accepted are not affected.
  void SetPeers(node::PeersConfig peers);

  struct Impl;

 private:
  AssociationRunner() = default;
  std::unique_ptr<Impl> impl_;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_ASSOCIATION_H_
