// DICOM TLS (PS3.15 Annex B; the BCP 195 profile) for the listener and for
// outgoing associations, on DCMTK's dcmtls. DCMTK stays out of this header:
// callers that use the layer include "dcmtk/dcmtls/tlslayer.h" themselves.
#ifndef INTERSLICE_SERVER_NET_DIMSE_TLS_H_
#define INTERSLICE_SERVER_NET_DIMSE_TLS_H_

#include <memory>

#include "absl/status/statusor.h"
#include "server/node/peer.h"

class DcmTLSTransportLayer;

namespace interslice::server::dimse {

struct DcmTlsDeleter {
  void operator()(DcmTLSTransportLayer* layer) const;
};
using DicomTlsLayer = std::unique_ptr<DcmTLSTransportLayer, DcmTlsDeleter>;

// A TLS transport layer for the acceptor (server_role true: the DICOM
// listener) or the requestor (false: C-STORE/C-GET to a peer), with:
//  - our certificate and key from `files` (PEM; both required, and they must
//    be a pair: peers check our certificate in both roles);
//  - the peer's certificate required and verified against
//    files.ca_certificates (PEM, required): an association from or to a
//    peer whose certificate no listed CA signed fails in the TLS handshake;
//  - the BCP 195 ciphersuites (TLS 1.2+), as DCMTK's tools default to.
// INVALID_ARGUMENT naming the file when one is missing or unusable. The
// layer can be shared by every association of the listener (or sender);
// hand it to DcmSCPConfig / DcmSCU::useSecureConnection (not owning).
absl::StatusOr<DicomTlsLayer> MakeDicomTls(const node::DicomTlsFiles& files,
                                           bool server_role);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_TLS_H_
