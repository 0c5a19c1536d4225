// The DICOMweb implementation of the node's PeerClient (server/node/peer.h):
// a QIDO-RS probe for Echo (client.h), QIDO-RS for Find and QIDO-RS +
// WADO-RS for Retrieve (pull.h), STOW-RS for Store (client.h), with the
// peer's own credentials and this server's timeouts (PeerClientSettings).
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_DICOMWEB_PEER_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_DICOMWEB_PEER_H_

#include <string>
#include <vector>

#include "server/node/peer.h"

namespace interslice::server::dicomweb {

class DicomWebPeerClient : public node::PeerClient {
 public:
  DicomWebPeerClient(node::DicomPeer peer, node::PeerClientSettings settings);

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
};

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_DICOMWEB_PEER_H_
