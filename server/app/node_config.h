// The DICOM node's configuration as the daemon takes it: the peers file
// and the rules file (server/node/config.h has their formats), checked
// together with the listener's AE titles; read once at start-up, again on
// SIGHUP, and by `--check-config`. Also the peers' clients: the one place
// that chooses a peer's protocol by its type.
#ifndef INTERSLICE_SERVER_APP_NODE_CONFIG_H_
#define INTERSLICE_SERVER_APP_NODE_CONFIG_H_

#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/app/server.h"
#include "server/base/audit.h"
#include "server/base/metrics.h"
#include "server/engine/job_manager.h"
#include "server/engine/spool.h"
#include "server/net/dimse/dimse_peer.h"
#include "server/net/dimse/pending_moves.h"
#include "server/net/dimse/storage_scp.h"
#include "server/node/config.h"
#include "server/node/peer.h"
#include "server/node/peer_registry.h"
#include "server/node/series_assembler.h"

namespace interslice::server {

// The node's configuration as a start would take it: the peers (the peers
// file, read by LoadPeers), the rules file (send_to names checked against
// the peers), the listener's AE titles, and every rule's called_ae among
// them.
struct DicomConfig {
  node::PeersConfig peers;
  node::RuleSet rules;
  std::vector<std::string> ae_titles;  // normalized; never empty
};

// The peers file's content; none without --dicom-peers.
absl::StatusOr<node::PeersConfig> LoadPeers(const ServerOptions& options);

// The rules file checked against `peers` and the --dicom-ae titles.
absl::StatusOr<DicomConfig> LoadDicomConfig(const ServerOptions& options,
                                            node::PeersConfig peers);

// A peer pulled from by C-MOVE sends to our listener: without one, no pull
// from it could ever succeed (FAILED_PRECONDITION naming the peer).
absl::Status CheckMoveDestination(const std::string& dicom_listen,
                                  const std::vector<node::DicomPeer>& peers);

// Outgoing associations call as the first --dicom-ae ("INTERSLICE" when
// none is given).
std::string CallingAeTitle(const ServerOptions& options);

// How this server talks to its DICOM peers: as the first --dicom-ae, with
// the --dicom-tls-* files for DIMSE peers marked tls; the timeouts are the
// defaults of PeerClientSettings.
node::PeerClientSettings PeerSettings(const ServerOptions& options);

// The peers' clients: DIMSE or DICOMweb by the peer's type (the one place
// that looks at it). `move`: our listener as the C-MOVE destination, or
// empty without one.
node::PeerClientFactory MakePeerClientFactory(node::PeerClientSettings settings,
                                              dimse::MoveDestination move);

// The series assembler on <spool>/dicom-in with `rules`, submitting its
// jobs to `manager` (owner "dicom").
absl::StatusOr<std::unique_ptr<node::SeriesAssembler>> StartDicomAssembler(
    const ServerOptions& options, node::RuleSet rules, Spool* spool,
    Metrics* metrics, JobManager* manager);

// The DICOM listener on --dicom-listen, accepting `peers`' callers.
absl::StatusOr<std::unique_ptr<dimse::StorageScp>> StartDicomListener(
    const ServerOptions& options, node::PeersConfig peers,
    node::SeriesAssembler* assembler, Metrics* metrics, AuditLog* audit,
    dimse::PendingMoves* pending_moves);

// SIGHUP: the peers and rules files read again and checked exactly as at
// start-up; the peers (the listener's accepted callers, and the registry
// every delivery, pull and query asks for its peer) and the assembler's
// rules are replaced only when all of it is valid. A delivery's next try
// goes to its peer's reloaded address; jobs already made keep their spec.
absl::Status ReloadDicomConfig(const ServerOptions& options,
                               node::SeriesAssembler* assembler,
                               dimse::StorageScp* listener,
                               node::PeerRegistry* peers);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_APP_NODE_CONFIG_H_
