#include "server/dicom/storage_scp.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/scppool.h"
#include "dcmtk/dcmnet/scpthrd.h"
#include "dcmtk/dcmtls/tlslayer.h"
#include "server/dicom/series_assembler.h"
#include "server/dicom/tls.h"
#include "server/log_safe.h"
#include "server/metrics.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dicom {
namespace {

std::string Trimmed(const char* text) {
  return std::string(absl::StripAsciiWhitespace(text == nullptr ? "" : text));
}

// A port the kernel considers free now (for --dicom-listen HOST:0): DCMTK's
// pool binds the port it is given and cannot report an ephemeral one. The
// window between this probe and DCMTK's bind is tiny; a lost race is a
// start-up error, never a wrong port.
absl::StatusOr<int> PickFreePort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return absl::InternalError("cannot create a socket");
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_ANY);
  addr.sin_port = 0;
  socklen_t len = sizeof(addr);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
    ::close(fd);
    return absl::UnavailableError("cannot find a free port for DICOM");
  }
  ::close(fd);
  return static_cast<int>(ntohs(addr.sin_port));
}

// Whether something is bound to `port` (DCMTK's listener, once it runs).
bool PortTaken(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return false;
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_ANY);
  addr.sin_port = htons(static_cast<uint16_t>(port));
  const bool taken =
      ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0 &&
      errno == EADDRINUSE;
  ::close(fd);
  return taken;
}

}  // namespace

std::vector<std::string> AcceptedStorageSopClasses() {
  // SEG and RTSTRUCT: segmentations drawn on a series held in the spool;
  // rules with `fill` make fill jobs of them (series_assembler.h).
  return {UID_CTImageStorage,
          UID_EnhancedCTImageStorage,
          UID_LegacyConvertedEnhancedCTImageStorage,
          UID_MRImageStorage,
          UID_EnhancedMRImageStorage,
          UID_LegacyConvertedEnhancedMRImageStorage,
          UID_SegmentationStorage,
          UID_RTStructureSetStorage};
}

struct StorageScp::Impl {
  StorageScpOptions options;
  SeriesAssembler* assembler = nullptr;
  Metrics* metrics = nullptr;
  DicomTlsLayer tls;
  std::unique_ptr<DcmBaseSCPPool> pool;
  std::thread thread;
  std::atomic<bool> finished{false};
  std::mutex mu;
  OFCondition result;
  bool stopped = false;

  void Count(const char* event) {
    if (metrics != nullptr) metrics->DicomEvent(event);
  }
};

namespace {

// One association: its AE titles, the series it stored into, and how it
// ended. DcmThreadSCP runs the DCMTK association state machine.
class AssociationScp : public DcmThreadSCP {
 public:
  explicit AssociationScp(StorageScp::Impl* impl) : impl_(impl) {}

 protected:
  OFBool checkCalledAETitleAccepted(const OFString& called) override {
    const std::string ae = Trimmed(called.c_str());
    for (const std::string& ours : impl_->options.ae_titles) {
      if (ours == ae) return OFTrue;
    }
    impl_->Count("associations_rejected");
    spdlog::warn(
        "dicom: association from {} rejected: called AE title {} "
        "is not served here",
        LogSafe(calling_), LogSafe(ae));
    return OFFalse;
  }

  OFBool checkCallingAETitleAccepted(const OFString& calling) override {
    const std::string ae = Trimmed(calling.c_str());
    if (impl_->options.peers.accept_unknown_callers) return OFTrue;
    for (const DicomPeer& peer : impl_->options.peers.peers) {
      if (peer.ae_title == ae) return OFTrue;
    }
    impl_->Count("associations_rejected");
    spdlog::warn(
        "dicom: association from calling AE title {} rejected: not "
        "in the peers file",
        LogSafe(ae));
    return OFFalse;
  }

  void notifyAssociationRequest(const T_ASC_Parameters& params,
                                DcmSCPActionType& action) override {
    calling_ = Trimmed(params.DULparams.callingAPTitle);
    called_ = Trimmed(params.DULparams.calledAPTitle);
    touched_.clear();
    stored_ = refused_ = 0;
    released_ = false;
    acknowledged_ = false;
    receiving_ = cut_off_ = false;
  }

  void notifyAssociationAcknowledge() override {
    acknowledged_ = true;
    impl_->Count("associations");
    spdlog::info("dicom: association {} -> {} accepted", LogSafe(calling_),
                 LogSafe(called_));
  }

  void notifyReleaseRequest() override { released_ = true; }

  // Called while a data set streams in: an instance larger than a whole
  // series may be is cut off here, by aborting the association, instead of
  // being written to the end first.
  void notifyRECEIVEProgress(const unsigned long bytes) override {
    if (receiving_ && !cut_off_ && static_cast<int64_t>(bytes) > allowance_) {
      cut_off_ = true;
      spdlog::warn(
          "dicom: association {} -> {} aborted: an instance passed {} bytes, "
          "the limit per series",
          LogSafe(calling_), LogSafe(called_), allowance_);
      abortAssociation();
    }
  }

  void notifyAssociationTermination() override {
    if (!acknowledged_) return;
    if (released_) {
      impl_->assembler->AssociationReleased(touched_);
    }
    spdlog::info(
        "dicom: association {} -> {} {}: {} instance(s) kept, {} refused",
        LogSafe(calling_), LogSafe(called_), released_ ? "released" : "aborted",
        stored_, refused_);
  }

  OFCondition handleIncomingCommand(
      T_DIMSE_Message* message,
      const DcmPresentationContextInfo& info) override {
    if (message->CommandField == DIMSE_C_STORE_RQ) {
      return HandleStore(message->msg.CStoreRQ, info);
    }
    return DcmThreadSCP::handleIncomingCommand(message, info);
  }

 private:
  OFCondition HandleStore(T_DIMSE_C_StoreRQ& request,
                          const DcmPresentationContextInfo& info) {
    const std::string staged = impl_->assembler->StagingPath();
    allowance_ = impl_->assembler->max_instance_bytes();
    receiving_ = true;
    OFCondition cond = receiveSTORERequest(request, info.presentationContextID,
                                           OFString(staged.c_str()));
    receiving_ = false;
    if (cut_off_ && cond.good()) cond = DUL_PEERABORTEDASSOCIATION;
    if (cond.bad()) {
      // The association ends (DcmSCP aborts it); nothing was acknowledged.
      // DCMTK's reason (network or parsing, no data-set values) says why.
      spdlog::warn("dicom: receiving an instance from {} failed: {}",
                   LogSafe(calling_), LogSafe(cond.text()));
      ::unlink(staged.c_str());
      return cond;
    }
    Uint16 status = STATUS_Success;
    if (info.abstractSyntax != request.AffectedSOPClassUID) {
      ::unlink(staged.c_str());
      status = STATUS_STORE_Error_DataSetDoesNotMatchSOPClass;
    } else {
      absl::StatusOr<std::string> key =
          impl_->assembler->AddInstance(calling_, called_, staged);
      if (key.ok()) {
        touched_.insert(*key);
      } else if (key.status().code() == absl::StatusCode::kResourceExhausted) {
        status = STATUS_STORE_Refused_OutOfResources;
        spdlog::warn("dicom: instance from {} refused (out of resources): {}",
                     LogSafe(calling_), LogSafe(key.status().message()));
      } else {
        status = STATUS_STORE_Error_CannotUnderstand;
        spdlog::warn("dicom: instance from {} refused: {}", LogSafe(calling_),
                     LogSafe(key.status().message()));
      }
    }
    if (status == STATUS_Success) {
      ++stored_;
      impl_->Count("instances_received");
    } else {
      ++refused_;
      impl_->Count("instances_refused");
    }
    return sendSTOREResponse(info.presentationContextID, request, status);
  }

  StorageScp::Impl* const impl_;
  std::string calling_, called_;
  std::set<std::string> touched_;
  int64_t stored_ = 0, refused_ = 0;
  bool released_ = false;
  bool acknowledged_ = false;
  bool receiving_ = false;
  bool cut_off_ = false;
  int64_t allowance_ = 0;
};

// DcmSCPPool<> default-constructs its workers; ours need the listener's
// state, so the pool is spelled out (the same three forwarding calls).
class Pool : public DcmBaseSCPPool {
 public:
  explicit Pool(StorageScp::Impl* impl) : impl_(impl) {}

 protected:
  struct Worker : public DcmBaseSCPPool::DcmBaseSCPWorker,
                  private AssociationScp {
    Worker(Pool& pool, StorageScp::Impl* impl)
        : DcmBaseSCPWorker(pool), AssociationScp(impl) {}
    OFCondition setSharedConfig(const DcmSharedSCPConfig& config) override {
      return AssociationScp::setSharedConfig(config);
    }
    OFBool busy() override { return AssociationScp::isConnected(); }
    OFCondition setAssociation(T_ASC_Association* assoc) override {
      handed_over_ = std::chrono::steady_clock::now();
      return DcmBaseSCPWorker::setAssociation(assoc);
    }
    OFCondition workerListen(T_ASC_Association* const assoc) override {
      OFCondition result = AssociationScp::run(assoc);
      // DCMTK 3.6.7's pool deletes a worker when its thread ends, while
      // the accepting thread may still be inside OFThread::start() writing
      // the new thread's id into that worker (a use after free, seen as
      // heap corruption after associations rejected within microseconds).
      // A worker therefore lives at least this long after it was handed
      // its association; start() has long returned by then.
      std::this_thread::sleep_until(handed_over_ +
                                    std::chrono::milliseconds(500));
      return result;
    }
    std::chrono::steady_clock::time_point handed_over_;
  };

  DcmBaseSCPWorker* createSCPWorker() override {
    return new Worker(*this, impl_);
  }

 private:
  StorageScp::Impl* const impl_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<StorageScp>> StorageScp::Start(
    const StorageScpOptions& options, SeriesAssembler* assembler,
    Metrics* metrics) {
  if (options.ae_titles.empty()) {
    return absl::InvalidArgumentError("the DICOM listener needs an AE title");
  }
  if (options.max_associations < 1 || options.max_associations > 1000) {
    return absl::InvalidArgumentError(
        "--dicom-max-associations must be between 1 and 1000");
  }
  // PS3.8: 0 means unlimited, which we never offer; DCMTK's floor is 4096.
  if (options.max_pdu_bytes < 4096 || options.max_pdu_bytes > 131072) {
    return absl::InvalidArgumentError(
        "--dicom-max-pdu must be between 4096 and 131072 bytes");
  }
  std::unique_ptr<StorageScp> scp(new StorageScp());
  scp->impl_ = std::make_unique<Impl>();
  Impl& impl = *scp->impl_;
  impl.options = options;
  impl.assembler = assembler;
  impl.metrics = metrics;

  const bool any_tls = !options.tls.certificate.empty() ||
                       !options.tls.private_key.empty() ||
                       !options.tls.ca_certificates.empty();
  if (any_tls) {
    absl::StatusOr<DicomTlsLayer> tls =
        MakeDicomTls(options.tls, /*server_role=*/true);
    if (!tls.ok()) return tls.status();
    impl.tls = *std::move(tls);
  }

  int port = options.port;
  if (port == 0) {
    absl::StatusOr<int> free_port = PickFreePort();
    if (!free_port.ok()) return free_port.status();
    port = *free_port;
  } else if (PortTaken(port)) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen for DICOM on port ", port, ": it is in use"));
  }

  auto pool = std::make_unique<Pool>(&impl);
  DcmSCPConfig& cfg = pool->getConfig();
  cfg.setPort(static_cast<Uint16>(port));
  cfg.setAETitle(options.ae_titles.front().c_str());
  // Several called AE titles: answer with the one that was called
  // (checkCalledAETitleAccepted decides which are served).
  cfg.setRespondWithCalledAETitle(OFTrue);
  cfg.setMaxReceivePDULength(options.max_pdu_bytes);
  // Non-blocking accept with a 1 s tick, so that Stop() is noticed.
  cfg.setConnectionBlockingMode(DUL_NOBLOCK);
  cfg.setConnectionTimeout(1);
  cfg.setDIMSEBlockingMode(DIMSE_NONBLOCKING);
  cfg.setDIMSETimeout(
      static_cast<Uint32>(std::max(1.0, options.dimse_timeout_seconds)));
  cfg.setACSETimeout(
      static_cast<Uint32>(std::max(1.0, options.acse_timeout_seconds)));
  cfg.setHostLookupEnabled(OFFalse);
  if (impl.tls) cfg.setTransportLayer(impl.tls.get());

  // Storage: exactly what the reader decodes. Compressed syntaxes first, so
  // that a sender is never asked to decompress what we can read as is.
  std::vector<TransferSyntaxInfo> decodable = DecodableTransferSyntaxes();
  OFList<OFString> storage_syntaxes;
  for (int pass = 0; pass < 2; ++pass) {
    for (const TransferSyntaxInfo& ts : decodable) {
      const bool encapsulated = DcmXfer(ts.uid.c_str()).isEncapsulated();
      if (encapsulated == (pass == 0)) {
        storage_syntaxes.push_back(ts.uid.c_str());
      }
    }
  }
  for (const std::string& sop : AcceptedStorageSopClasses()) {
    OFCondition cond =
        cfg.addPresentationContext(sop.c_str(), storage_syntaxes);
    if (cond.bad()) {
      return absl::InternalError(
          absl::StrCat("DICOM listener set-up: ", cond.text()));
    }
  }
  OFList<OFString> echo_syntaxes;
  echo_syntaxes.push_back(UID_LittleEndianExplicitTransferSyntax);
  echo_syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  echo_syntaxes.push_back(UID_BigEndianExplicitTransferSyntax);
  OFCondition cond =
      cfg.addPresentationContext(UID_VerificationSOPClass, echo_syntaxes);
  if (cond.bad()) {
    return absl::InternalError(
        absl::StrCat("DICOM listener set-up: ", cond.text()));
  }
  pool->setMaxThreads(static_cast<Uint16>(options.max_associations));
  impl.pool = std::move(pool);

  Impl* raw = &impl;
  impl.thread = std::thread([raw] {
    OFCondition result = raw->pool->listen();
    std::lock_guard<std::mutex> lock(raw->mu);
    raw->result = result;
    raw->finished = true;
  });
  // Ready once DCMTK holds the port (or failed to take it).
  const auto give_up =
      std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!impl.finished && !PortTaken(port) &&
         std::chrono::steady_clock::now() < give_up) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (impl.finished || !PortTaken(port)) {
    impl.pool->stopAfterCurrentAssociations();
    impl.thread.join();
    std::lock_guard<std::mutex> lock(impl.mu);
    return absl::UnavailableError(absl::StrCat(
        "cannot listen for DICOM on port ", port, ": ", impl.result.text()));
  }
  scp->port_ = port;
  std::string titles;
  for (const std::string& ae : options.ae_titles) {
    absl::StrAppend(&titles, titles.empty() ? "" : ", ", ae);
  }
  spdlog::info(
      "dicom: listening on port {} as {}{} ({} peer(s), at most {} "
      "association(s))",
      port, LogSafe(titles), impl.tls ? " with TLS" : "",
      options.peers.peers.size(), options.max_associations);
  return scp;
}

StorageScp::~StorageScp() { Stop(); }

void StorageScp::Stop() {
  if (!impl_) return;
  {
    std::lock_guard<std::mutex> lock(impl_->mu);
    if (impl_->stopped) return;
    impl_->stopped = true;
  }
  impl_->pool->stopAfterCurrentAssociations();
  if (impl_->thread.joinable()) impl_->thread.join();
  spdlog::info("dicom: listener stopped");
}

}  // namespace interslice::server::dicom
