#include "server/net/dimse/store.h"

#include <algorithm>
#include <filesystem>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/dicom/series_reader.h"
#include "server/net/dimse/associate.h"
#include "server/net/dimse/scu.h"
#include "server/net/dimse/tls.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/dimse.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/dstorscu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dimse {

using node::DicomPeer;
using node::PeerLabel;
using node::StoreResult;

namespace fs = std::filesystem;
namespace {

bool Accepted(Uint16 status) {
  return status == STATUS_Success || DICOM_WARNING_STATUS(status);
}

// DcmStorageSCU reports each instance's response here; we count them and
// keep the first refusal's status text (no UIDs in it).
class CountingStorageScu : public DcmStorageSCU {
 public:
  StoreResult result;
  // Protected in DcmSCU (3.6.7); dcmtls' TLS layer goes in through it.
  using DcmStorageSCU::useSecureConnection;

 protected:
  void notifySOPInstanceSent(const TransferEntry& entry) override {
    if (!entry.RequestSent) return;  // counted as refused afterwards
    if (Accepted(entry.ResponseStatusCode)) {
      ++result.accepted;
      return;
    }
    ++result.refused;
    if (result.first_refusal.empty()) {
      result.first_refusal =
          absl::StrFormat("0x%04X %s", entry.ResponseStatusCode,
                          DU_cstoreStatusString(entry.ResponseStatusCode));
    }
  }
};

}  // namespace

namespace {

// `files` over one association after another (one DcmStorageSCU).
absl::StatusOr<StoreResult> StoreFilesSequentially(
    const DicomPeer& peer, const std::vector<std::string>& files,
    const StoreOptions& options) {
  CountingStorageScu scu;
  ConfigureScu(scu, peer, options.calling_ae_title, options.max_pdu_bytes,
               options.timeout_seconds);
  // Keep sending after a refused instance: the rest may well be accepted,
  // and the refusal is reported.
  scu.setHaltOnUnsuccessfulStoreMode(OFFalse);
  absl::StatusOr<DicomTlsLayer> tls_or = TlsLayerFor(peer, options.tls);
  if (!tls_or.ok()) return tls_or.status();
  DicomTlsLayer tls = *std::move(tls_or);
  for (const std::string& file : files) {
    const OFCondition cond =
        scu.addDicomFile(OFFilename(file.c_str()), ERM_fileOnly,
                         /*checkValues=*/OFFalse);
    if (cond.bad()) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot send ", fs::path(file).filename().string(), ": ",
                       cond.text()));
    }
  }
  if (scu.getNumberOfSOPInstances() == 0) return StoreResult{};
  OFCondition cond = scu.addPresentationContexts();
  if (cond.bad()) {
    return absl::InternalError(
        absl::StrCat("cannot propose presentation contexts: ", cond.text()));
  }
  if (absl::Status s = OpenNetwork(scu, peer, tls); !s.ok()) return s;
  // One association per group of at most 128 presentation contexts
  // (DcmStorageSCU groups them); bounded so that a peer that accepts an
  // association but no context cannot keep us here.
  const size_t rounds = scu.getNumberOfSOPInstances() + 1;
  for (size_t round = 0;
       round < rounds && scu.getNumberOfSOPInstancesToBeSent() > 0; ++round) {
    if (round > 0) {
      // The contexts of what is left: releaseAssociation() dropped the
      // last round's association parameters (without this, the next
      // negotiation failed with "ASC Caller passed in a NULL key", and a
      // peer that refused one SOP class made the whole delivery UNAVAILABLE).
      cond = scu.addPresentationContexts();
      if (cond == NET_EC_NoSOPInstancesToSend ||
          cond == NET_EC_NoPresentationContextsDefined) {
        break;
      }
      if (cond.bad()) {
        return absl::InternalError(absl::StrCat(
            "cannot propose presentation contexts: ", cond.text()));
      }
    }
    cond = scu.negotiateAssociation();
    if (cond == NET_EC_NoSOPInstancesToSend) break;
    // What is left was refused in an earlier round's negotiation and the
    // peer accepts none of it now either: counted as refused below.
    if (round > 0 && cond == NET_EC_NoAcceptablePresentationContexts) break;
    if (cond.bad()) return AssociationError(peer, cond);
    cond = scu.sendSOPInstances();
    scu.releaseAssociation();
    if (cond.bad() && cond != NET_EC_NoSOPInstancesToSend) {
      return absl::UnavailableError(absl::StrCat("sending to ", PeerLabel(peer),
                                                 " failed: ", cond.text()));
    }
  }
  StoreResult result = scu.result;
  const int total = static_cast<int>(scu.getNumberOfSOPInstances());
  const int unsent = total - result.accepted - result.refused;
  if (unsent > 0) {
    result.refused += unsent;
    if (result.first_refusal.empty()) {
      result.first_refusal = absl::StrCat(
          unsent,
          " instance(s) not sent: the peer accepted no presentation "
          "context for their SOP class");
    }
  }
  return result;
}

}  // namespace

absl::StatusOr<StoreResult> StoreFiles(const DicomPeer& peer,
                                       const std::vector<std::string>& files,
                                       const StoreOptions& options) {
  // With DCMTK's decoders registered, DcmStorageSCU proposes a lossless
  // encapsulated file (an RLE intensity series, --dicom-compression rle)
  // together with the uncompressed syntaxes, and decompresses it for a peer
  // that accepts only those; without them it proposes RLE alone. Once,
  // before any sending thread starts (it changes DCMTK's global codec list).
  RegisterDicomDecoders();
  const size_t lanes = std::min<size_t>(
      files.size(), static_cast<size_t>(std::max(1, peer.max_associations)));
  if (lanes <= 1) return StoreFilesSequentially(peer, files, options);
  // Dealt round-robin: the sorted list holds series one after another, so
  // each lane gets a share of every series and of the large objects (SEG,
  // Encapsulated STL) rather than one lane all of them.
  std::vector<std::vector<std::string>> shares(lanes);
  for (size_t i = 0; i < files.size(); ++i) {
    shares[i % lanes].push_back(files[i]);
  }
  std::vector<absl::StatusOr<StoreResult>> results(lanes, StoreResult{});
  {
    std::vector<std::thread> threads;
    threads.reserve(lanes);
    for (size_t lane = 0; lane < lanes; ++lane) {
      threads.emplace_back([&, lane] {
        results[lane] = StoreFilesSequentially(peer, shares[lane], options);
      });
    }
    for (std::thread& t : threads) t.join();
  }
  // One lane that failed fails the try (the queue retries every file; the
  // instances other lanes stored are stored again, which a PACS replaces);
  // INVALID_ARGUMENT (an unreadable file) before UNAVAILABLE, as the
  // sequential path would have found it before associating.
  StoreResult total;
  const absl::Status* first_error = nullptr;
  for (const absl::StatusOr<StoreResult>& r : results) {
    if (!r.ok()) {
      if (first_error == nullptr ||
          (r.status().code() == absl::StatusCode::kInvalidArgument &&
           first_error->code() != absl::StatusCode::kInvalidArgument)) {
        first_error = &r.status();
      }
      continue;
    }
    total.accepted += r->accepted;
    total.refused += r->refused;
    if (total.first_refusal.empty()) total.first_refusal = r->first_refusal;
  }
  if (first_error != nullptr) return *first_error;
  return total;
}

}  // namespace interslice::server::dimse
