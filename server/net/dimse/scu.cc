#include "server/net/dimse/scu.h"

#include <cstdlib>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/scu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dimse {

using node::DicomPeer;
using node::DicomTlsFiles;
using node::PeerLabel;

void DisableNagleOnOutgoingAssociations() {
  // Overwrites: an inherited TCP_NODELAY=0 would bring the stalls back.
  ::setenv("TCP_NODELAY", "1", /*overwrite=*/1);
}

void ConfigureScu(DcmSCU& scu, const DicomPeer& peer,
                  const std::string& calling_ae_title, uint32_t max_pdu_bytes,
                  int timeout_seconds) {
  scu.setAETitle(calling_ae_title.c_str());
  scu.setPeerAETitle(peer.ae_title.c_str());
  scu.setPeerHostName(peer.host.c_str());
  scu.setPeerPort(static_cast<Uint16>(peer.port));
  scu.setMaxReceivePDULength(max_pdu_bytes);
  scu.setACSETimeout(static_cast<Uint32>(timeout_seconds));
  scu.setDIMSETimeout(static_cast<Uint32>(timeout_seconds));
  scu.setDIMSEBlockingMode(DIMSE_NONBLOCKING);
  scu.setConnectionTimeout(timeout_seconds);
}

absl::StatusOr<DicomTlsLayer> TlsLayerFor(const DicomPeer& peer,
                                          const DicomTlsFiles& files) {
  if (!peer.tls) return DicomTlsLayer();
  absl::StatusOr<DicomTlsLayer> layer = MakeDicomTls(files, false);
  if (!layer.ok()) {
    return absl::FailedPreconditionError(absl::StrCat(
        PeerLabel(peer), " needs TLS: ", layer.status().message()));
  }
  return layer;
}

}  // namespace interslice::server::dimse
