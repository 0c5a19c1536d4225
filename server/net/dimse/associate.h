// How every outgoing association of ours begins (C-ECHO, C-FIND, C-GET,
// C-MOVE, C-STORE): the network, the TLS layer when the peer uses one, and
// the negotiation, each failure one line naming the peer. For the DIMSE
// SCUs of this folder (it includes DCMTK); DcmSCU keeps useSecureConnection
// protected, so each SCU class makes it public and these templates call it.
#ifndef INTERSLICE_SERVER_NET_DIMSE_ASSOCIATE_H_
#define INTERSLICE_SERVER_NET_DIMSE_ASSOCIATE_H_

#include "absl/status/status.h"
#include "server/net/dimse/tls.h"
#include "server/node/peer.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/scu.h"

namespace interslice::server::dimse {

// INTERNAL: the network could not be initialised.
absl::Status InitNetworkError(const OFCondition& cond);
// INTERNAL naming the peer: the TLS layer was refused.
absl::Status TlsLayerError(const node::DicomPeer& peer,
                           const OFCondition& cond);
// UNAVAILABLE naming the peer: the association was not made.
absl::Status AssociationError(const node::DicomPeer& peer,
                              const OFCondition& cond);

// initNetwork, then the TLS layer when `tls` holds one (it must outlive the
// association). The presentation contexts are added before.
template <typename Scu>
absl::Status OpenNetwork(Scu& scu, const node::DicomPeer& peer,
                         const DicomTlsLayer& tls) {
  OFCondition cond = scu.initNetwork();
  if (cond.bad()) return InitNetworkError(cond);
  if (tls != nullptr) {
    cond = scu.useSecureConnection(tls.get());
    if (cond.bad()) return TlsLayerError(peer, cond);
  }
  return absl::OkStatus();
}

// OpenNetwork, then the negotiation: the association is up.
template <typename Scu>
absl::Status Associate(Scu& scu, const node::DicomPeer& peer,
                       const DicomTlsLayer& tls) {
  if (absl::Status s = OpenNetwork(scu, peer, tls); !s.ok()) return s;
  const OFCondition cond = scu.negotiateAssociation();
  if (cond.bad()) return AssociationError(peer, cond);
  return absl::OkStatus();
}

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_ASSOCIATE_H_
