#include "server/net/dimse/find.h"

#include <cctype>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/net/dimse/associate.h"
#include "server/net/dimse/scu.h"
#include "server/net/dimse/tls.h"
#include "server/node/peer.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/dimse.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/scu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dimse {

using node::CheckFindQuery;
using node::DicomPeer;
using node::FindQuery;
using node::FindResult;
using node::FoundSeries;
using node::FoundStudy;
using node::PeerLabel;

namespace {

// DICOM text from the peer, made valid UTF-8 for the answer (protobuf
// strings must be): the data set was converted to UTF-8 when DCMTK could;
// any byte that still is not ASCII becomes '?'.
std::string Text(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  std::string text(value.c_str(), value.length());
  bool ascii = true;
  for (const char c : text) ascii &= static_cast<unsigned char>(c) < 0x80;
  if (!ascii) {
    // convertToUTF8() succeeded when SpecificCharacterSet says ISO_IR 192.
    OFString charset;
    item.findAndGetOFString(DCM_SpecificCharacterSet, charset);
    if (charset != "ISO_IR 192") {
      for (char& c : text) {
        if (static_cast<unsigned char>(c) >= 0x80) c = '?';
      }
    }
  }
  return text;
}

// C-FIND with a cap on the answers kept (see find.h).
class FindScu : public DcmSCU {
 public:
  using DcmSCU::useSecureConnection;  // protected in DcmSCU (3.6.7)

  // One query: at most `cap` matches go to `on_match`.
  void Begin(int cap, std::function<void(DcmDataset&)> on_match) {
    cap_ = cap;
    kept_ = 0;
    after_cancel_ = 0;
    cancelled_ = false;
    truncated = false;
    final_status = 0;
    on_match_ = std::move(on_match);
  }
  bool truncated = false;
  Uint16 final_status = 0;
  bool ignored_cancel = false;

 protected:
  OFCondition handleFINDResponse(const T_ASC_PresentationContextID pc,
                                 QRResponse* response,
                                 OFBool& wait_for_next) override {
    wait_for_next = DICOM_PENDING_STATUS(response->m_status);
    if (!wait_for_next) {
      final_status = response->m_status;
      return EC_Normal;
    }
    if (kept_ < cap_) {
      ++kept_;
      if (response->m_dataset != nullptr) {
        response->m_dataset->convertToUTF8();
        on_match_(*response->m_dataset);
      }
      return EC_Normal;
    }
    truncated = true;
    if (!cancelled_) {
      cancelled_ = true;
      sendCANCELRequest(pc);
      return EC_Normal;
    }
    // Some peers ignore C-CANCEL: bounded, then the association goes.
    if (++after_cancel_ > cap_) {
      ignored_cancel = true;
      return makeOFCondition(OFM_dcmnet, 0x201, OF_error,
                             "the peer went on answering after C-CANCEL");
    }
    return EC_Normal;
  }

 private:
  int cap_ = 0;
  int kept_ = 0;
  int after_cancel_ = 0;
  bool cancelled_ = false;
  std::function<void(DcmDataset&)> on_match_;
};

}  // namespace

absl::StatusOr<FindResult> FindStudiesAndSeries(const DicomPeer& peer,
                                                const FindQuery& query,
                                                const FindOptions& options) {
  if (absl::Status s = CheckFindQuery(query); !s.ok()) return s;
  FindScu scu;
  ConfigureScu(scu, peer, options.calling_ae_title, options.max_pdu_bytes,
               options.timeout_seconds);
  OFList<OFString> syntaxes;
  syntaxes.push_back(UID_LittleEndianExplicitTransferSyntax);
  syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  scu.addPresentationContext(UID_FINDStudyRootQueryRetrieveInformationModel,
                             syntaxes);
  absl::StatusOr<DicomTlsLayer> tls_or = TlsLayerFor(peer, options.tls);
  if (!tls_or.ok()) return tls_or.status();
  DicomTlsLayer tls = *std::move(tls_or);
  // The presentation context of Study Root C-FIND on a new association.
  T_ASC_PresentationContextID pc = 0;
  // DcmSCU drops its association parameters at release: initNetwork()
  // again before each association (without it the second one failed with
  // "ASC Caller passed in a NULL key").
  auto associate = [&]() -> absl::Status {
    if (absl::Status s = Associate(scu, peer, tls); !s.ok()) return s;
    pc = scu.findPresentationContextID(
        UID_FINDStudyRootQueryRetrieveInformationModel, "");
    if (pc == 0) {
      scu.releaseAssociation();
      return absl::FailedPreconditionError(
          absl::StrCat(PeerLabel(peer), " does not offer C-FIND (Study Root)"));
    }
    return absl::OkStatus();
  };
  if (absl::Status s = associate(); !s.ok()) return s;
  // One C-FIND; the association ends on any error.
  auto run = [&](DcmDataset& keys, int cap, const char* level,
                 std::function<void(DcmDataset&)> on_match) -> absl::Status {
    scu.Begin(cap, std::move(on_match));
    const OFCondition c = scu.sendFINDRequest(pc, &keys, nullptr);
    if (c.bad()) {
      scu.abortAssociation();
      if (scu.ignored_cancel) {
        return absl::OkStatus();  // truncated, what was kept stands
      }
      return absl::UnavailableError(absl::StrCat(
          "C-FIND (", level, ") on ", PeerLabel(peer), " failed: ", c.text()));
    }
    const Uint16 status = scu.final_status;
    const bool cancelled = status == STATUS_FIND_Cancel;
    if (status != STATUS_Success && !cancelled &&
        !DICOM_WARNING_STATUS(status)) {
      if (scu.isConnected()) scu.releaseAssociation();
      return absl::FailedPreconditionError(absl::StrFormat(
          "%s refused the C-FIND (%s): 0x%04X %s", PeerLabel(peer), level,
          status, DU_cfindStatusString(status)));
    }
    return absl::OkStatus();
  };

  FindResult result;
  DcmDataset study_keys;
  study_keys.putAndInsertString(DCM_QueryRetrieveLevel, "STUDY");
  study_keys.putAndInsertString(DCM_StudyInstanceUID, "");
  study_keys.putAndInsertString(DCM_PatientID, query.patient_id.c_str());
  study_keys.putAndInsertString(DCM_StudyDate, query.study_date.c_str());
  study_keys.putAndInsertString(DCM_AccessionNumber,
                                query.accession_number.c_str());
  study_keys.putAndInsertString(DCM_ModalitiesInStudy, query.modality.c_str());
  study_keys.putAndInsertString(DCM_StudyDescription, "");
  absl::Status s =
      run(study_keys, options.max_studies, "study level", [&](DcmDataset& d) {
        FoundStudy study;
        study.study_instance_uid = Text(d, DCM_StudyInstanceUID);
        study.patient_id = Text(d, DCM_PatientID);
        study.study_date = Text(d, DCM_StudyDate);
        study.accession_number = Text(d, DCM_AccessionNumber);
        study.study_description = Text(d, DCM_StudyDescription);
        study.modalities = Text(d, DCM_ModalitiesInStudy);
        if (!study.study_instance_uid.empty()) {
          result.studies.push_back(std::move(study));
        }
      });
  if (!s.ok()) return s;
  result.truncated = scu.truncated;
  if (scu.truncated) {
    // A C-CANCEL that crossed the peer's last answer arrives after the
    // C-FIND ended; a peer may take that stray command for a protocol
    // error. The series queries get a new association.
    if (scu.isConnected()) scu.releaseAssociation();
    if (absl::Status a = associate(); !a.ok()) return a;
  }

  int series_left = options.max_series;
  for (FoundStudy& study : result.studies) {
    if (series_left <= 0) {
      result.truncated = true;
      break;
    }
    DcmDataset series_keys;
    series_keys.putAndInsertString(DCM_QueryRetrieveLevel, "SERIES");
    series_keys.putAndInsertString(DCM_StudyInstanceUID,
                                   study.study_instance_uid.c_str());
    series_keys.putAndInsertString(DCM_SeriesInstanceUID, "");
    series_keys.putAndInsertString(DCM_Modality, query.modality.c_str());
    series_keys.putAndInsertString(DCM_SeriesNumber, "");
    series_keys.putAndInsertString(DCM_SeriesDescription, "");
    series_keys.putAndInsertString(DCM_NumberOfSeriesRelatedInstances, "");
    s = run(series_keys, series_left, "series level", [&](DcmDataset& d) {
      FoundSeries series;
      series.series_instance_uid = Text(d, DCM_SeriesInstanceUID);
      series.modality = Text(d, DCM_Modality);
      series.series_number = Text(d, DCM_SeriesNumber);
      series.series_description = Text(d, DCM_SeriesDescription);
      Sint32 instances = -1;
      if (d.findAndGetSint32(DCM_NumberOfSeriesRelatedInstances, instances)
              .good()) {
        series.instances = instances;
      }
      if (!series.series_instance_uid.empty()) {
        study.series.push_back(std::move(series));
      }
    });
    if (!s.ok()) return s;
    series_left -= static_cast<int>(study.series.size());
    result.truncated |= scu.truncated;
  }
  if (scu.isConnected()) scu.releaseAssociation();
  return result;
}

}  // namespace interslice::server::dimse
