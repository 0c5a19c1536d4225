// The peers in force: the peers file's content (and the peers given on the
// command line) with one PeerClient each, read once at start-up and
// replaced whole by a SIGHUP reload. Every user asks it at the moment it
// needs a peer: the listener which callers it accepts, the outbox where a
// delivery goes, a job where its series comes from, the Find RPC whom to
// ask. A call in progress keeps the client it was given (shared), so a
// reload never changes the peer of an association or request already
// under way; the next try of a delivery uses the reloaded address.
//
// It also serves the engine's pull of JobSpec.pacs_source
// (engine/peer_services.h). Thread-safe.
#ifndef INTERSLICE_SERVER_NODE_PEER_REGISTRY_H_
#define INTERSLICE_SERVER_NODE_PEER_REGISTRY_H_

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/engine/peer_services.h"
#include "server/node/config.h"
#include "server/node/peer.h"

namespace interslice::server::node {

class PeerRegistry : public PeerSeriesSource {
 public:
  explicit PeerRegistry(PeerClientFactory factory, PeersConfig peers = {});

  // Replaces every peer (start-up, reload): each gets a new client.
  void SetPeers(PeersConfig peers);

  // The configuration in force (who may associate, and from where).
  std::shared_ptr<const PeersConfig> config() const;
  // The client of the peer named `name`, or null.
  std::shared_ptr<PeerClient> Find(const std::string& name) const;
  // Every peer's client, in the file's order.
  std::vector<std::shared_ptr<PeerClient>> clients() const;
  bool empty() const;

  // INVALID_ARGUMENT naming the first name that is not a configured peer,
  // and the configured ones ("send_to names an unknown DICOM peer ...").
  absl::Status CheckPeers(const std::vector<std::string>& names) const;

  // PeerSeriesSource.
  absl::Status CheckPeer(const std::string& name) const override;
  absl::StatusOr<RetrievedSeries> Retrieve(
      const v1::PacsSeriesSource& source, const std::string& dest_dir,
      int64_t max_bytes, const CancellationToken* cancel) override;

 private:
  struct Generation {
    std::shared_ptr<const PeersConfig> config;
    std::vector<std::shared_ptr<PeerClient>> clients;
  };
  std::shared_ptr<const Generation> generation() const;

  const PeerClientFactory factory_;
  mutable std::mutex mu_;
  std::shared_ptr<const Generation> generation_;  // guarded by mu_
};

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_PEER_REGISTRY_H_
