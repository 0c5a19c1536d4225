// Storing files on a DIMSE peer (Storage SCU, DCMTK DcmStorageSCU): the
// DIMSE side of PeerClient::Store (server/node/peer.h; a DICOMweb peer takes
// them by STOW-RS instead, server/net/dicomweb/client.h).
//
// Contract: the files are dealt round-robin into min(peer.max_associations,
// files) shares sent at once, each by a DcmStorageSCU of its own over as
// many associations as it needs (it proposes each file's SOP class with its
// own transfer syntax, plus the uncompressed ones, and splits at 128
// presentation contexts): so never more than max_associations associations
// with the peer at a time. A share that fails fails the call (the outbox's
// retry sends every file again); the counts are the sums of the shares'. It
// returns how many instances the peer accepted (DIMSE success or warning)
// and, for the first refusal, the peer's status ("0xA700 Refused: Out of
// resources"). A peer that cannot be reached or rejects the association is
// UNAVAILABLE naming the peer; files that cannot be read are
// INVALID_ARGUMENT. Never retries by itself. Blocking.
#ifndef INTERSLICE_SERVER_NET_DIMSE_STORE_H_
#define INTERSLICE_SERVER_NET_DIMSE_STORE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/peer.h"

namespace interslice::server::dimse {

struct StoreOptions {
  // Our AE title on outgoing associations.
  std::string calling_ae_title = "INTERSLICE";
  // TCP connect, association and DIMSE timeouts.
  int timeout_seconds = 30;
  uint32_t max_pdu_bytes = 65536;
  // Our certificate, key and CA for peers with tls: true.
  node::DicomTlsFiles tls;
};

absl::StatusOr<node::StoreResult> StoreFiles(
    const node::DicomPeer& peer, const std::vector<std::string>& files,
    const StoreOptions& options);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_STORE_H_
