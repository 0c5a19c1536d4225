#include "server/dicom/retrieve.h"

#include <fcntl.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/dicom/series_reader.h"
#include "server/dicom/dataset_scan.h"
#include "server/dicom/scu.h"
#include "server/dicom/tls.h"
#include "server/dicomweb/pull.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/dimse.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/scu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dicom {
namespace fs = std::filesystem;
namespace {

// The image storage classes the reader turns into volumes.
const char* const kStorageClasses[] = {
    UID_CTImageStorage,
    UID_EnhancedCTImageStorage,
    UID_LegacyConvertedEnhancedCTImageStorage,
    UID_MRImageStorage,
    UID_EnhancedMRImageStorage,
    UID_LegacyConvertedEnhancedMRImageStorage,
};

bool SyncPath(const std::string& path, bool directory) {
  const int fd =
      ::open(path.c_str(), directory ? O_RDONLY | O_DIRECTORY : O_RDONLY);
  if (fd < 0) return false;
  const bool ok = ::fsync(fd) == 0;
  ::close(fd);
  return ok;
}

// C-GET with the sub-operations' instances written durably into a folder,
// within the limits.
class GetScu : public DcmSCU {
 public:
  GetScu(std::string dest, const RetrieveOptions& options)
      : dest_(std::move(dest)), options_(options) {}

  int64_t instances = 0;
  int64_t bytes = 0;
  absl::Status error = absl::OkStatus();
  // Protected in DcmSCU (3.6.7); dcmtls' TLS layer goes in through it.
  using DcmSCU::useSecureConnection;

 protected:
  // Bit-preserving (setStorageMode): DCMTK writes each sub-operation's data
  // set to a file of our naming as it arrives (never the peer's SOP Instance
  // UID as a name), unparsed; the file is scanned (dataset_scan.h) before
  // anything in the server process parses it, so a hostile peer cannot
  // exhaust a parser's stack (issue 22). DCMTK answers success when this
  // returns a good condition, "cannot understand" (and ends the retrieval)
  // otherwise; `error` says why.
  OFCondition handleSTORERequestFile(T_ASC_PresentationContextID* presID,
                                     const OFString& /*peer_named*/,
                                     T_DIMSE_C_StoreRQ* request) override {
    const std::string name = absl::StrFormat("pacs-%06d.dcm", instances + 1);
    const std::string path = (fs::path(dest_) / name).string();
    const std::string temp = path + ".part";
    OFCondition cond =
        DcmSCU::handleSTORERequestFile(presID, OFString(temp.c_str()), request);
    std::error_code ec;
    auto refuse = [&](absl::Status why) {
      fs::remove(temp, ec);
      if (error.ok()) error = std::move(why);
      return makeOFCondition(OFM_dcmnet, 0x200, OF_error,
                             "instance refused by the retriever");
    };
    if (!error.ok()) return refuse(error);
    if (cond.bad()) {
      fs::remove(temp, ec);
      return cond;  // DCMTK deleted it; a network or disk error
    }
    if (instances + 1 > options_.max_instances) {
      return refuse(absl::ResourceExhaustedError(absl::StrCat(
          "the series on the peer has more than ", options_.max_instances,
          " instances (the server's limit per job)")));
    }
    const int64_t size = static_cast<int64_t>(fs::file_size(temp, ec));
    if (ec || !SyncPath(temp, false)) {
      return refuse(absl::InternalError(
          "cannot write a retrieved instance to the job's folder: write/sync "
          "failed"));
    }
    if (bytes + size > options_.max_bytes) {
      return refuse(absl::ResourceExhaustedError(absl::StrCat(
          "the series on the peer is larger than ", options_.max_bytes,
          " bytes (the server's upload limit per job)")));
    }
    if (absl::StatusOr<DatasetScanResult> scan = ScanPart10File(temp);
        !scan.ok()) {
      return refuse(absl::InvalidArgumentError(absl::StrCat(
          "an instance from the peer was refused: ", scan.status().message())));
    }
    fs::rename(temp, path, ec);
    if (ec) {
      return refuse(absl::InternalError("cannot rename a retrieved instance"));
    }
    ++instances;
    bytes += size;
    return EC_Normal;
  }

 private:
  const std::string dest_;
  const RetrieveOptions options_;
};

}  // namespace

absl::StatusOr<RetrieveResult> RetrieveSeries(
    const DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const RetrieveOptions& options) {
  if (peer.type == PeerType::kDicomWeb) {
    return dicomweb::RetrieveSeriesWeb(peer, study_instance_uid,
                                       series_instance_uid, dest_dir, options);
  }
  if (study_instance_uid.empty() || series_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "pacs_source needs study_instance_uid and series_instance_uid");
  }
  GetScu scu(dest_dir, options);
  ConfigureScu(scu, peer, options.calling_ae_title, options.max_pdu_bytes,
               options.timeout_seconds);
  scu.setStorageMode(DCMSCU_STORAGE_BIT_PRESERVING);
  scu.setStorageDir(OFString(dest_dir.c_str()));

  OFList<OFString> model_syntaxes;
  model_syntaxes.push_back(UID_LittleEndianExplicitTransferSyntax);
  model_syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  scu.addPresentationContext(UID_GETStudyRootQueryRetrieveInformationModel,
                             model_syntaxes);
  OFList<OFString> image_syntaxes;
  for (const TransferSyntaxInfo& ts : DecodableTransferSyntaxes()) {
    image_syntaxes.push_back(ts.uid.c_str());
  }
  for (const char* sop_class : kStorageClasses) {
    scu.addPresentationContext(sop_class, image_syntaxes, ASC_SC_ROLE_SCP);
  }

  absl::StatusOr<DicomTlsLayer> tls_or = TlsLayerFor(peer, options.tls);
  if (!tls_or.ok()) return tls_or.status();
  DicomTlsLayer tls = *std::move(tls_or);
  OFCondition cond = scu.initNetwork();
  if (cond.bad()) {
    return absl::InternalError(
        absl::StrCat("cannot initialise the network: ", cond.text()));
  }
  if (tls != nullptr) {
    cond = scu.useSecureConnection(tls.get());
    if (cond.bad()) {
      return absl::InternalError(absl::StrCat(
          "cannot use TLS with ", PeerLabel(peer), ": ", cond.text()));
    }
  }
  cond = scu.negotiateAssociation();
  if (cond.bad()) {
    return absl::UnavailableError(absl::StrCat(
        "cannot associate with ", PeerLabel(peer), ": ", cond.text()));
  }
  const T_ASC_PresentationContextID pc = scu.findPresentationContextID(
      UID_GETStudyRootQueryRetrieveInformationModel, "");
  if (pc == 0) {
    scu.releaseAssociation();
    return absl::FailedPreconditionError(
        absl::StrCat(PeerLabel(peer),
                     " does not offer C-GET (Study Root); the server "
                     "retrieves with C-GET only"));
  }
  DcmDataset query;
  query.putAndInsertString(DCM_QueryRetrieveLevel, "SERIES");
  query.putAndInsertString(DCM_StudyInstanceUID, study_instance_uid.c_str());
  query.putAndInsertString(DCM_SeriesInstanceUID, series_instance_uid.c_str());
  OFList<RetrieveResponse*> responses;
  cond = scu.sendCGETRequest(pc, &query, &responses);
  Uint16 final_status = 0;
  int failed = 0;
  if (!responses.empty()) {
    const RetrieveResponse* last = responses.back();
    final_status = last->m_status;
    failed = last->m_numberOfFailedSubops;
  }
  for (RetrieveResponse* r : responses) delete r;
  if (scu.isConnected()) scu.releaseAssociation();
  SyncPath(dest_dir, true);

  if (!scu.error.ok()) return scu.error;
  if (cond.bad()) {
    return absl::UnavailableError(
        absl::StrCat("C-GET from ", PeerLabel(peer), " failed: ", cond.text()));
  }
  if (final_status != STATUS_Success && !DICOM_WARNING_STATUS(final_status)) {
    return absl::FailedPreconditionError(
        absl::StrFormat("%s refused the C-GET: 0x%04X %s", PeerLabel(peer),
                        final_status, DU_cgetStatusString(final_status)));
  }
  if (failed > 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        PeerLabel(peer), " could not send ", failed,
        " instance(s) of the series (failed C-GET sub-operations)"));
  }
  if (scu.instances == 0) {
    return absl::NotFoundError(absl::StrCat(
        PeerLabel(peer), " has no CT or MR instance of the requested series"));
  }
  return RetrieveResult{scu.instances, scu.bytes};
}

}  // namespace interslice::server::dicom
