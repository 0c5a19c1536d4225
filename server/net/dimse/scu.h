// What outgoing associations (C-STORE delivery, C-GET retrieval) share: how
// a peer is named in messages, how a DcmSCU is pointed at it, and its TLS
// layer. DCMTK stays out of this header (DcmSCU is only declared).
#ifndef INTERSLICE_SERVER_NET_DIMSE_SCU_H_
#define INTERSLICE_SERVER_NET_DIMSE_SCU_H_

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "server/net/dimse/tls.h"
#include "server/node/peer.h"

class DcmSCU;

namespace interslice::server::dimse {

// Turns Nagle's algorithm off on every socket DCMTK connects for an
// outgoing association (DcmSCU, DcmStorageSCU: delivery, retrieval, TLS or
// not). DIMSE is request/response: with Nagle on, each message's last
// segment waits for the peer's delayed acknowledgement, about 40 ms, twice
// an instance (issue 25: 17 instances/s sent instead of hundreds). DCMTK
// 3.6.7 has no API or global for it: dcmnet's dulfsm.cc reads the
// environment variable TCP_NODELAY (getenv, at every connection) and sets
// the socket option when it is non-zero; so this sets TCP_NODELAY=1 in our
// environment (job workers inherit it; harmless there). setenv races with
// getenv in other threads: call it once at the very start of main(), before
// any thread exists. (The listener's accepted sockets are our own accept
// loop's, which sets the option itself: connection_gate.cc.)
void DisableNagleOnOutgoingAssociations();

// Points `scu` at `peer`, calling as `calling_ae_title`: the largest PDU
// we receive, and `timeout_seconds` for connecting, the association and each
// DIMSE message (non-blocking DIMSE, so a silent peer cannot hang us).
void ConfigureScu(DcmSCU& scu, const node::DicomPeer& peer,
                  const std::string& calling_ae_title, uint32_t max_pdu_bytes,
                  int timeout_seconds);

// The requestor TLS layer for `peer` from `files`, or null when the peer
// does not use TLS. FAILED_PRECONDITION naming the peer when TLS is needed
// but `files` cannot make a layer.
absl::StatusOr<DicomTlsLayer> TlsLayerFor(const node::DicomPeer& peer,
                                          const node::DicomTlsFiles& files);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_SCU_H_
