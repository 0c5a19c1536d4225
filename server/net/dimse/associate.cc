#include "server/net/dimse/associate.h"

#include "absl/strings/str_cat.h"

namespace interslice::server::dimse {

absl::Status InitNetworkError(const OFCondition& cond) {
  return absl::InternalError(
      absl::StrCat("cannot initialise the network: ", cond.text()));
}

absl::Status TlsLayerError(const node::DicomPeer& peer,
                           const OFCondition& cond) {
  return absl::InternalError(absl::StrCat(
      "cannot use TLS with ", node::PeerLabel(peer), ": ", cond.text()));
}

absl::Status AssociationError(const node::DicomPeer& peer,
                              const OFCondition& cond) {
  return absl::UnavailableError(absl::StrCat(
      "cannot associate with ", node::PeerLabel(peer), ": ", cond.text()));
}

}  // namespace interslice::server::dimse
