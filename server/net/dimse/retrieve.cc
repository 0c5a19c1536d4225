#include "server/net/dimse/retrieve.h"

#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "server/base/log_safe.h"
#include "server/net/dimse/associate.h"
#include "server/net/dimse/pending_moves.h"
#include "server/net/dimse/scu.h"
#include "server/net/dimse/tls.h"
#include "server/node/dataset_scan.h"
#include "spdlog/spdlog.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/dimse.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/scu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dimse {
namespace fs = std::filesystem;

using node::DatasetScanResult;
using node::DicomPeer;
using node::PeerLabel;
using node::RetrieveMethod;
using node::RetrieveResult;
using node::ScanPart10File;
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

// DcmSCU with the TLS layer settable from outside.
class RetrieveScu : public DcmSCU {
 public:
  // Protected in DcmSCU (3.6.7); dcmtls' TLS layer goes in through it.
  using DcmSCU::useSecureConnection;
};

// C-GET with the sub-operations' instances written durably into a folder,
// within the limits.
class GetScu : public RetrieveScu {
 public:
  GetScu(std::string dest, const node::RetrieveLimits& limits)
      : dest_(std::move(dest)), limits_(limits) {}

  int64_t instances = 0;
  int64_t bytes = 0;
  absl::Status error = absl::OkStatus();

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
    if (instances + 1 > limits_.max_instances) {
      return refuse(absl::ResourceExhaustedError(absl::StrCat(
          "the series on the peer has more than ", limits_.max_instances,
          " instances (the server's limit per job)")));
    }
    const int64_t size = static_cast<int64_t>(fs::file_size(temp, ec));
    if (ec || !SyncPath(temp, false)) {
      return refuse(absl::InternalError(
          "cannot write a retrieved instance to the job's folder: write/sync "
          "failed"));
    }
    if (bytes + size > limits_.max_bytes) {
      return refuse(absl::ResourceExhaustedError(absl::StrCat(
          "the series on the peer is larger than ", limits_.max_bytes,
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
  const node::RetrieveLimits limits_;
};

// The C-MOVE (see retrieve.h): the instances arrive at our listener, which
// hands them to `move` (pending_moves.h); this waits for the final response
// and for the storing associations to end. Returns the move's result;
// the caller deletes what arrived on error.
absl::StatusOr<RetrieveResult> MoveSeries(const DicomPeer& peer,
                                          const std::string& study_uid,
                                          const std::string& series_uid,
                                          PendingMoves::Move& move,
                                          const RetrieveOptions& options) {
  RetrieveScu scu;
  ConfigureScu(scu, peer, options.calling_ae_title, options.max_pdu_bytes,
               options.timeout_seconds);
  OFList<OFString> model_syntaxes;
  model_syntaxes.push_back(UID_LittleEndianExplicitTransferSyntax);
  model_syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  scu.addPresentationContext(UID_MOVEStudyRootQueryRetrieveInformationModel,
                             model_syntaxes);
  scu.addPresentationContext(UID_FINDStudyRootQueryRetrieveInformationModel,
                             model_syntaxes);
  absl::StatusOr<DicomTlsLayer> tls_or = TlsLayerFor(peer, options.tls);
  if (!tls_or.ok()) return tls_or.status();
  DicomTlsLayer tls = *std::move(tls_or);
  if (absl::Status s = Associate(scu, peer, tls); !s.ok()) return s;
  const T_ASC_PresentationContextID pc = scu.findPresentationContextID(
      UID_MOVEStudyRootQueryRetrieveInformationModel, "");
  if (pc == 0) {
    scu.releaseAssociation();
    return absl::FailedPreconditionError(absl::StrCat(
        PeerLabel(peer),
        " does not offer C-MOVE (Study Root); set retrieve: get for it in "
        "the peers file if it offers C-GET"));
  }
  DcmDataset query;
  query.putAndInsertString(DCM_QueryRetrieveLevel, "SERIES");
  query.putAndInsertString(DCM_StudyInstanceUID, study_uid.c_str());
  query.putAndInsertString(DCM_SeriesInstanceUID, series_uid.c_str());
  // A PACS may answer a C-MOVE of a series it lacks and one to a move
  // destination it does not know alike (Orthanc 1.10: 0xC000, no
  // sub-operations, no comment); a C-FIND first tells them apart, when
  // the peer offers it.
  if (const T_ASC_PresentationContextID find_pc = scu.findPresentationContextID(
          UID_FINDStudyRootQueryRetrieveInformationModel, "");
      find_pc != 0) {
    DcmDataset keys(query);
    OFList<QRResponse*> found;
    const OFCondition find = scu.sendFINDRequest(find_pc, &keys, &found);
    int matches = 0;
    Uint16 find_status = 0;
    for (QRResponse* r : found) {
      if (DICOM_PENDING_STATUS(r->m_status) && r->m_dataset != nullptr) {
        ++matches;
      }
      find_status = r->m_status;
      delete r;
    }
    if (find.good() && find_status == STATUS_Success && matches == 0) {
      scu.releaseAssociation();
      return absl::NotFoundError(
          absl::StrCat(PeerLabel(peer),
                       " has no instance of the requested series (its "
                       "C-FIND matches no such series)"));
    }
  }
  OFList<RetrieveResponse*> responses;
  const OFCondition cond = scu.sendMOVERequest(
      pc, OFString(options.move_destination_ae.c_str()), &query, &responses);
  bool answered = false;
  Uint16 final_status = 0;
  int64_t completed = 0, failed = 0, warnings = 0;
  if (!responses.empty()) {
    const RetrieveResponse* last = responses.back();
    answered = true;
    final_status = last->m_status;
    completed = last->m_numberOfCompletedSubops;
    failed = last->m_numberOfFailedSubops;
    warnings = last->m_numberOfWarningSubops;
  }
  for (RetrieveResponse* r : responses) delete r;
  if (scu.isConnected()) scu.releaseAssociation();

  if (cond.bad() || !answered) {
    return absl::UnavailableError(
        absl::StrCat("C-MOVE from ", PeerLabel(peer),
                     " failed: ", cond.bad() ? cond.text() : "no response"));
  }
  if (!move.error().ok()) return move.error();
  if (final_status == STATUS_MOVE_Refused_MoveDestinationUnknown) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "%s refused the C-MOVE: 0x%04X move destination unknown: it does "
        "not know this server's AE title '%s' (add it, with the listener's "
        "host and port, to its DICOM nodes; Orthanc: DicomModalities)",
        PeerLabel(peer), final_status, options.move_destination_ae));
  }
  // The storing associations end after (or about when) the final response
  // arrives: wait for them, so that what we count is what came.
  const bool settled = move.WaitSettled(
      completed, std::chrono::steady_clock::now() +
                     std::chrono::seconds(options.timeout_seconds));
  if (!move.error().ok()) return move.error();
  const int64_t received = move.instances();
  if (final_status != STATUS_Success && !DICOM_WARNING_STATUS(final_status)) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "%s refused the C-MOVE to move destination '%s': 0x%04X %s (%d "
        "sent, %d failed)%s",
        PeerLabel(peer), options.move_destination_ae, final_status,
        DU_cmoveStatusString(final_status), completed, failed,
        completed + failed + warnings == 0
            ? "; a PACS answers so when it does not know the move "
              "destination: add this AE title, with the listener's host and "
              "port, to its DICOM nodes (Orthanc: DicomModalities)"
            : ""));
  }
  if (failed > 0 || warnings > 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        PeerLabel(peer), " could not send the whole series by C-MOVE: ", failed,
        " failed and ", warnings, " warning sub-operation(s), ", completed,
        " completed"));
  }
  if (!settled) {
    return absl::DeadlineExceededError(absl::StrCat(
        "C-MOVE from ", PeerLabel(peer), ": ",
        received < completed
            ? absl::StrCat("only ", received, " of the ", completed,
                           " instance(s) it reported sent arrived at this "
                           "server's listener")
            : std::string("its storing association(s) did not end"),
        " within ", options.timeout_seconds, " s of its final response"));
  }
  if (received != completed) {
    return absl::FailedPreconditionError(
        absl::StrCat(PeerLabel(peer), " reported ", completed,
                     " instance(s) sent by C-MOVE, but ", received,
                     " arrived at this server's listener"));
  }
  if (received == 0) {
    return absl::NotFoundError(
        absl::StrCat(PeerLabel(peer),
                     " has no instance of the requested series (C-MOVE "
                     "sent none)"));
  }
  return RetrieveResult{received, move.bytes()};
}

}  // namespace

absl::StatusOr<node::RetrieveResult> RetrieveSeries(
    const DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits, const RetrieveOptions& options) {
  if (study_instance_uid.empty() || series_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "pacs_source needs study_instance_uid and series_instance_uid");
  }
  if (peer.retrieve == RetrieveMethod::kMove) {
    if (options.pending_moves == nullptr ||
        options.move_destination_ae.empty()) {
      return absl::FailedPreconditionError(absl::StrCat(
          PeerLabel(peer),
          " is retrieved from by C-MOVE (retrieve: move), which needs the "
          "server's DICOM listener (--dicom-listen) as the move "
          "destination"));
    }
    const auto wait_until = std::chrono::steady_clock::now() +
                            std::chrono::seconds(limits.move_wait_seconds);
    bool waited = false;
    absl::StatusOr<std::shared_ptr<PendingMoves::Move>> move =
        options.pending_moves->Register(
            peer.ae_title, study_instance_uid, series_instance_uid, dest_dir,
            limits.max_instances, limits.max_bytes, [&]() -> absl::Status {
              if (!waited) {
                spdlog::info(
                    "{}: another job is moving the same series; this one "
                    "waits for it",
                    LogSafe(PeerLabel(peer)));
                waited = true;
              }
              if (limits.cancel != nullptr) {
                INTERSLICE_RETURN_IF_ERROR(limits.cancel->Check());
              }
              if (std::chrono::steady_clock::now() >= wait_until) {
                return absl::FailedPreconditionError(absl::StrCat(
                    "another job has been moving the same series from ",
                    PeerLabel(peer), " for over ", limits.move_wait_seconds,
                    " s; try again when it has finished"));
              }
              return absl::OkStatus();
            });
    if (!move.ok()) return move.status();
    absl::StatusOr<RetrieveResult> result = MoveSeries(
        peer, study_instance_uid, series_instance_uid, **move, options);
    // From here on, late instances of this move are refused (never handed
    // to the rules).
    options.pending_moves->Close(*move);
    SyncPath(dest_dir, true);
    if (!result.ok()) {
      (*move)->RemoveKept();  // nothing of a failed move stays
    }
    return result;
  }
  GetScu scu(dest_dir, limits);
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
  if (absl::Status s = Associate(scu, peer, tls); !s.ok()) return s;
  const T_ASC_PresentationContextID pc = scu.findPresentationContextID(
      UID_GETStudyRootQueryRetrieveInformationModel, "");
  if (pc == 0) {
    scu.releaseAssociation();
    return absl::FailedPreconditionError(
        absl::StrCat(PeerLabel(peer),
                     " does not offer C-GET (Study Root); if it offers "
                     "C-MOVE, set retrieve: move for it in the peers file"));
  }
  DcmDataset query;
  query.putAndInsertString(DCM_QueryRetrieveLevel, "SERIES");
  query.putAndInsertString(DCM_StudyInstanceUID, study_instance_uid.c_str());
  query.putAndInsertString(DCM_SeriesInstanceUID, series_instance_uid.c_str());
  OFList<RetrieveResponse*> responses;
  OFCondition cond = scu.sendCGETRequest(pc, &query, &responses);
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

}  // namespace interslice::server::dimse
