#include "server/net/dimse/echo.h"

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/scu.h"
#include "dcmtk/dcmtls/tlslayer.h"
#include "server/net/dimse/associate.h"
#include "server/net/dimse/scu.h"
#include "server/net/dimse/tls.h"

namespace interslice::server::dimse {

using node::DicomPeer;
using node::DicomTlsFiles;
using node::PeerLabel;

namespace {

// DcmSCU with its TLS hook public (DCMTK 3.6.7 keeps it protected).
class EchoScu : public DcmSCU {
 public:
  using DcmSCU::useSecureConnection;
};

}  // namespace

absl::Status EchoPeer(const DicomPeer& peer,
                      const std::string& calling_ae_title,
                      const DicomTlsFiles& tls_files, int timeout_seconds) {
  EchoScu scu;
  ConfigureScu(scu, peer, calling_ae_title, /*max_pdu_bytes=*/16384,
               timeout_seconds);
  OFList<OFString> syntaxes;
  syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  OFCondition cond =
      scu.addPresentationContext(UID_VerificationSOPClass, syntaxes);
  if (cond.bad()) {
    return absl::InternalError(absl::StrCat(
        "cannot propose Verification to ", PeerLabel(peer), ": ", cond.text()));
  }
  absl::StatusOr<DicomTlsLayer> tls_or = TlsLayerFor(peer, tls_files);
  if (!tls_or.ok()) return tls_or.status();
  DicomTlsLayer tls = *std::move(tls_or);
  if (absl::Status s = Associate(scu, peer, tls); !s.ok()) return s;
  cond = scu.sendECHORequest(0);
  scu.releaseAssociation();
  if (cond.bad()) {
    return absl::UnavailableError(
        absl::StrCat("C-ECHO of ", PeerLabel(peer), " failed: ", cond.text()));
  }
  return absl::OkStatus();
}

}  // namespace interslice::server::dimse
