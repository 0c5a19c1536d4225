// The DIMSE implementation of the node's PeerClient (server/node/peer.h):
// C-ECHO (echo.h), Study Root C-FIND (find.h), C-GET or C-MOVE by the
// peer's `retrieve` (retrieve.h) and C-STORE (store.h), with this server's
// AE title, TLS files and timeouts (PeerClientSettings).
#ifndef INTERSLICE_SERVER_NET_DIMSE_DIMSE_PEER_H_
#define INTERSLICE_SERVER_NET_DIMSE_DIMSE_PEER_H_

#include <string>
#include <vector>

#include "server/node/peer.h"

namespace interslice::server::dimse {

class PendingMoves;

// Where a peer with `retrieve: move` sends a series: our listener, called
// as `ae_title`, which routes the instances through `pending_moves`. Empty:
// the server runs no listener (such pulls fail, saying why).
struct MoveDestination {
  std::string ae_title;
  PendingMoves* pending_moves = nullptr;
};

class DimsePeerClient : public node::PeerClient {
 public:
  DimsePeerClient(node::DicomPeer peer, node::PeerClientSettings settings,
                  MoveDestination move_destination = {});

  absl::Status Echo() override;
  std::string EchoName() const override;
  std::string EchoAnswered() const override;
  absl::StatusOr<node::FindResult> Find(
      const node::FindQuery& query, const node::FindLimits& limits) override;
  absl::StatusOr<node::RetrieveResult> Retrieve(
      const std::string& study_instance_uid,
      const std::string& series_instance_uid, const std::string& dest_dir,
      const node::RetrieveLimits& limits) override;
  absl::StatusOr<node::StoreResult> Store(
      const std::vector<std::string>& files) override;
  node::PeerSummary Summary() const override;

 private:
  const node::PeerClientSettings settings_;
  const MoveDestination move_destination_;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_DIMSE_PEER_H_
