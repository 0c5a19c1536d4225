#include "server/dicom/delivery.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/dicom/series_reader.h"
#include "server/dicom/scu.h"
#include "server/dicom/tls.h"
#include "server/dicomweb/client.h"
#include "spdlog/spdlog.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/dimse.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/dstorscu.h"
#include "dcmtk/dcmtls/tlslayer.h"

namespace interslice::server::dicom {
namespace fs = std::filesystem;
namespace {

int64_t NowMillis() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

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

std::vector<std::string> ListDicomFiles(const std::string& dir) {
  std::vector<std::string> files;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end;
       it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::ifstream in(it->path(), std::ios::binary);
    char magic[132] = {};
    if (in.read(magic, sizeof(magic)) &&
        std::string(magic + 128, 4) == "DICM") {
      files.push_back(it->path().string());
    }
  }
  std::sort(files.begin(), files.end());
  return files;
}

namespace {

// `files` over one association after another (one DcmStorageSCU).
absl::StatusOr<StoreResult> StoreFilesSequentially(
    const DicomPeer& peer, const std::vector<std::string>& files,
    const DeliveryOptions& options) {
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
  cond = scu.initNetwork();
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
    if (cond.bad()) {
      return absl::UnavailableError(absl::StrCat(
          "cannot associate with ", PeerLabel(peer), ": ", cond.text()));
    }
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
                                       const DeliveryOptions& options) {
  // A DICOMweb peer takes the files by STOW-RS (server/dicomweb/client.h).
  if (peer.type == PeerType::kDicomWeb) {
    return dicomweb::StowFiles(peer, files, options);
  }
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

DeliveryQueue::DeliveryQueue(std::vector<DicomPeer> peers,
                             DeliveryOptions options, OnUpdate on_update,
                             DeliveryCounters counters)
    : peers_(std::move(peers)),
      options_(std::move(options)),
      on_update_(std::move(on_update)),
      counters_(std::move(counters)) {}

DeliveryQueue::~DeliveryQueue() { Stop(); }

void DeliveryQueue::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  if (thread_.joinable()) return;
  stopping_ = false;
  thread_ = std::thread([this] { Loop(); });
}

void DeliveryQueue::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

std::optional<DicomPeer> DeliveryQueue::FindPeer(
    const std::string& name) const {
  for (const DicomPeer& p : peers_) {
    if (p.name == name) return p;
  }
  return std::nullopt;
}

absl::Status DeliveryQueue::CheckPeers(
    const std::vector<std::string>& names) const {
  for (const std::string& name : names) {
    const bool known =
        std::any_of(peers_.begin(), peers_.end(),
                    [&](const DicomPeer& p) { return p.name == name; });
    if (!known) {
      std::vector<std::string> configured;
      for (const DicomPeer& p : peers_) configured.push_back(p.name);
      return absl::InvalidArgumentError(absl::StrCat(
          "send_to names an unknown DICOM peer \"", name, "\" (configured: ",
          configured.empty() ? "none; see --dicom-peers"
                             : absl::StrJoin(configured, ", "),
          ")"));
    }
  }
  return absl::OkStatus();
}

void DeliveryQueue::Add(const std::string& job_id, v1::Delivery state,
                        std::vector<std::string> files,
                        int64_t first_added_unix_ms) {
  if (state.state() == v1::Delivery::DELIVERED ||
      state.state() == v1::Delivery::FAILED) {
    return;
  }
  state.set_state(v1::Delivery::PENDING);
  state.set_instances_total(static_cast<int32_t>(files.size()));
  {
    std::lock_guard<std::mutex> lock(mu_);
    Entry& entry = entries_[{job_id, state.peer()}];
    entry.job_id = job_id;
    entry.state = std::move(state);
    entry.files = std::move(files);
    entry.first_added_unix_ms = first_added_unix_ms;
  }
  cv_.notify_all();
}

void DeliveryQueue::Forget(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mu_);
  for (auto it = entries_.begin(); it != entries_.end();) {
    it = it->first.first == job_id ? entries_.erase(it) : std::next(it);
  }
}

int DeliveryQueue::pending() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(entries_.size());
}

void DeliveryQueue::Loop() {
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    const int64_t now = NowMillis();
    int64_t next = std::numeric_limits<int64_t>::max();
    auto due = entries_.end();
    for (auto it = entries_.begin(); it != entries_.end(); ++it) {
      const int64_t at = it->second.state.next_attempt_unix_ms();
      if (at <= now) {
        due = it;
        break;
      }
      next = std::min(next, at);
    }
    if (due == entries_.end()) {
      if (next == std::numeric_limits<int64_t>::max()) {
        cv_.wait(lock);
      } else {
        cv_.wait_for(lock, std::chrono::milliseconds(next - now));
      }
      continue;
    }
    const auto key = due->first;
    Entry entry = due->second;
    lock.unlock();
    Try(entry);
    lock.lock();
    auto it = entries_.find(key);
    if (it == entries_.end()) continue;  // forgotten meanwhile
    if (entry.state.state() == v1::Delivery::PENDING) {
      it->second.state = entry.state;
    } else {
      entries_.erase(it);
    }
    lock.unlock();
    on_update_(entry.job_id, entry.state);
    lock.lock();
  }
}

void DeliveryQueue::Try(Entry& entry) {
  v1::Delivery& d = entry.state;
  d.set_attempts(d.attempts() + 1);
  // Recorded before the try: a process killed during it (kill -9, power
  // cut) still counts the attempt after its restart.
  on_update_(entry.job_id, d);
  const auto peer =
      std::find_if(peers_.begin(), peers_.end(),
                   [&](const DicomPeer& p) { return p.name == d.peer(); });
  const auto started = std::chrono::steady_clock::now();
  absl::StatusOr<StoreResult> result =
      peer == peers_.end()
          ? absl::FailedPreconditionError(absl::StrCat(
                "peer ", d.peer(), " is no longer in the peers file"))
          : StoreFiles(*peer, entry.files, options_);
  const int64_t now = NowMillis();
  const int total = static_cast<int>(entry.files.size());
  d.set_instances_total(total);
  if (result.ok()) {
    d.set_instances_sent(result->accepted);
    if (counters_.sent && result->accepted > 0) {
      counters_.sent(d.peer(), result->accepted);
    }
    if (counters_.failed && result->refused > 0) {
      counters_.failed(d.peer(), result->refused);
    }
  } else if (counters_.failed) {
    counters_.failed(d.peer(), total);
  }
  if (result.ok() && result->refused == 0 && result->accepted == total) {
    d.set_state(v1::Delivery::DELIVERED);
    d.clear_last_error();
    d.set_next_attempt_unix_ms(0);
    const double seconds = std::chrono::duration<double>(
                               std::chrono::steady_clock::now() - started)
                               .count();
    spdlog::info(
        "job={} delivered to peer {}: {} instance(s) in {:.2f} s ({:.1f} "
        "instances/s), attempt {}",
        entry.job_id, d.peer(), total, seconds,
        seconds > 0 ? total / seconds : 0.0, d.attempts());
    return;
  }
  d.set_last_error(result.ok() ? absl::StrCat(result->refused, " of ", total,
                                              " instance(s) refused: ",
                                              result->first_refusal)
                               : std::string(result.status().message()));
  if (now - entry.first_added_unix_ms >= options_.give_up_after.count()) {
    d.set_state(v1::Delivery::FAILED);
    d.set_next_attempt_unix_ms(0);
    spdlog::warn(
        "job={} delivery to peer {} failed for good after {} "
        "attempt(s): {}",
        entry.job_id, d.peer(), d.attempts(), d.last_error());
    return;
  }
  // Exponential backoff, capped.
  int64_t backoff = options_.initial_backoff.count();
  for (int i = 1; i < d.attempts() && backoff < options_.max_backoff.count();
       ++i) {
    backoff *= 2;
  }
  backoff = std::min<int64_t>(backoff, options_.max_backoff.count());
  d.set_state(v1::Delivery::PENDING);
  d.set_next_attempt_unix_ms(now + backoff);
  spdlog::warn(
      "job={} delivery to peer {} failed (attempt {}), next try in "
      "{} ms: {}",
      entry.job_id, d.peer(), d.attempts(), backoff, d.last_error());
}

}  // namespace interslice::server::dicom
