// C-ECHO of a peer (DICOM PS3.7 9.3.5, the Verification service): is the
// peer reachable, does it accept our AE title, and (for a tls peer) does the
// TLS handshake succeed. Used by `interslice-server --check-config` and at
// start-up (server/app/server.cc); DCMTK stays behind echo.cc.
#ifndef INTERSLICE_SERVER_NET_DIMSE_ECHO_H_
#define INTERSLICE_SERVER_NET_DIMSE_ECHO_H_

#include <string>

#include "absl/status/status.h"
#include "server/node/peer.h"

namespace interslice::server::dimse {

// One association with `peer`, calling as `calling_ae_title`, proposing
// Verification only; one C-ECHO; release. `timeout_seconds` bounds the
// connection, the association and the answer each. OK when the peer
// answered status 0x0000; otherwise UNAVAILABLE (connection refused or
// timed out, association rejected or aborted), FAILED_PRECONDITION (TLS
// needed but the files cannot make a layer) or INTERNAL, with one line
// naming the peer (PeerLabel) and what failed. (A DICOMweb peer is probed
// with a QIDO-RS search instead: dicomweb::ProbeDicomWebPeer, the same
// codes, PERMISSION_DENIED for refused credentials.)
absl::Status EchoPeer(const node::DicomPeer& peer,
                      const std::string& calling_ae_title,
                      const node::DicomTlsFiles& tls, int timeout_seconds);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_ECHO_H_
