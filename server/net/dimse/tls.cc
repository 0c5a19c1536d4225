#include "server/net/dimse/tls.h"

#include <filesystem>
#include <mutex>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/assoc.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dimse {

using node::DicomTlsFiles;

namespace {

absl::Status Check(const OFCondition& cond, const std::string& what) {
  if (cond.good()) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("DICOM TLS: ", what, ": ", cond.text()));
}

}  // namespace

void DcmTlsDeleter::operator()(DcmTLSTransportLayer* layer) const {
  delete layer;
}

absl::StatusOr<DicomTlsLayer> MakeDicomTls(const DicomTlsFiles& files,
                                           bool server_role) {
  for (const auto& [path, what] :
       {std::pair{&files.certificate, "certificate"},
        std::pair{&files.private_key, "private key"},
        std::pair{&files.ca_certificates, "CA certificates"}}) {
    if (path->empty()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "DICOM TLS needs a certificate, its key and the CA certificates "
          "that sign peer certificates; the ",
          what, " file is not given"));
    }
    std::error_code ec;
    if (!std::filesystem::is_regular_file(*path, ec)) {
      return absl::InvalidArgumentError(
          absl::StrCat("DICOM TLS: ", what, " file ", *path, " not found"));
    }
  }
  // OpenSSL is initialised once per process, however many layers exist.
  static std::once_flag openssl_once;
  bool first = false;
  std::call_once(openssl_once, [&first] { first = true; });
  DicomTlsLayer layer(
      new DcmTLSTransportLayer(server_role ? NET_ACCEPTOR : NET_REQUESTOR,
                               /*randFile=*/nullptr, first ? OFTrue : OFFalse));
  if (!*layer) {
    return absl::InternalError("DICOM TLS: cannot create an OpenSSL context");
  }
  absl::Status s =
      Check(layer->setTLSProfile(TSP_Profile_BCP195), "the BCP 195 profile");
  if (s.ok()) s = Check(layer->activateCipherSuites(), "the ciphersuites");
  if (s.ok()) {
    s = Check(
        layer->setPrivateKeyFile(files.private_key.c_str(), DCF_Filetype_PEM),
        "private key " + files.private_key);
  }
  if (s.ok()) {
    s = Check(
        layer->setCertificateFile(files.certificate.c_str(), DCF_Filetype_PEM),
        "certificate " + files.certificate);
  }
  if (s.ok() && !layer->checkPrivateKeyMatchesCertificate()) {
    s = absl::InvalidArgumentError(
        absl::StrCat("DICOM TLS: private key ", files.private_key,
                     " does not match certificate ", files.certificate));
  }
  if (s.ok()) {
    s = Check(layer->addTrustedCertificateFile(files.ca_certificates.c_str(),
                                               DCF_Filetype_PEM),
              "CA certificates " + files.ca_certificates);
  }
  if (!s.ok()) return s;
  layer->setCertificateVerification(DCV_requireCertificate);
  return layer;
}

}  // namespace interslice::server::dimse
