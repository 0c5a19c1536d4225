#include "server/net/dimse/association.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <mutex>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"
#include "core/dicom/series_reader.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcxfer.h"
#include "dcmtk/dcmnet/assoc.h"
#include "dcmtk/dcmnet/cond.h"
#include "dcmtk/dcmnet/dcmlayer.h"
#include "dcmtk/dcmnet/dcmtrans.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/dul.h"
#include "dcmtk/dcmnet/scpthrd.h"
#include "dcmtk/dcmtls/tlslayer.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "server/net/dimse/pending_moves.h"
#include "server/net/dimse/tls.h"
#include "server/node/config.h"
#include "server/node/intake.h"
#include "server/node/outcome.h"
#include "server/node/received_instance.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dimse {

using node::DicomPeer;
using node::InNetwork;
using node::PeersConfig;
using node::ReadReceivedInstance;
using node::ReceivedInstance;
using node::SourceNetwork;

namespace {

// PS3.5 table 6.2-1: an AE title holds characters of the default
// repertoire (printable ASCII) except the backslash, and no control
// characters. What a title breaks otherwise (found by dicom_listener_fuzzer:
// a calling AE title with bytes >= 0x80 made the series' origin.json, which
// is JSON and so UTF-8, throw and stop the server), it is refused at the
// association instead. The reason names no byte of the title.
const char* AeTitleFault(const std::string& ae) {
  for (const char c : ae) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 || u > 0x7E) {
      return "has a character outside the default repertoire (PS3.5 6.2)";
    }
    if (c == '\\') return "has a backslash (PS3.5 6.2)";
  }
  return nullptr;
}

std::string Trimmed(const char* text) {
  return std::string(absl::StripAsciiWhitespace(text == nullptr ? "" : text));
}

// DCMTK reads dcmExternalSocketHandle once per ASC_receiveAssociation,
// before it asks the network's transport layer for the connection object;
// the mutex is held from setting it until then (same thread).
std::mutex g_external_socket_mu;

struct Handover {
  ReadyConnection* connection = nullptr;
  std::unique_lock<std::mutex>* lock = nullptr;
  AssociationRunner::Impl* runner = nullptr;
  bool reached = false;  // DCMTK asked for the connection (and owns fd)
};
thread_local Handover t_handover;

}  // namespace

struct AssociationRunner::Impl {
  StorageScpOptions options;
  node::Intake* intake = nullptr;
  Metrics* metrics = nullptr;
  RefusalLog* refusals = nullptr;
  ConnectionGate* gate = nullptr;
  DicomTlsLayer tls;
  std::unique_ptr<DcmTransportLayer> layer;
  T_ASC_Network* network = nullptr;
  DcmSharedSCPConfig config;
  // The peers in force (replaced whole by SetPeers on a reload); each
  // association checks its caller against one snapshot.
  std::mutex peers_mu;
  std::shared_ptr<const PeersConfig> peers;

  std::shared_ptr<const PeersConfig> Peers() {
    std::lock_guard<std::mutex> lock(peers_mu);
    return peers;
  }

  void Count(const char* event, double n = 1) {
    if (metrics != nullptr) metrics->DicomEvent(event, n);
  }
};

namespace {

// What DCMTK reads and writes for one association: replays the bytes the
// gate read, feeds every byte to the connection's PduGuard before handing
// it on, and moves the watched deadline as PDUs begin and end.
class GuardedConnection : public DcmTransportConnection {
 public:
  GuardedConnection(int fd, DcmTransportConnection* inner,
                    ReadyConnection& from, AssociationRunner::Impl* runner)
      : DcmTransportConnection(fd),
        inner_(inner),
        replay_(std::move(from.preread)),
        guard_(std::move(from.guard)),
        watch_(from.watch),
        source_(from.source),
        runner_(runner) {
    if (guard_ == nullptr) guard_ = std::make_unique<PduGuard>();
  }
  ~GuardedConnection() override {
    Unwatch();
    delete inner_;
  }

  OFCondition serverSideHandshake() override {
    OFCondition c = inner_->serverSideHandshake();
    if (c.bad() && (watch_ == nullptr || !watch_->cut())) {
      runner_->refusals->Refused(
          refusal::kTls, source_,
          absl::StrCat("TLS handshake failed: ", c.text()));
    }
    return c;
  }
  OFCondition clientSideHandshake() override {
    return inner_->clientSideHandshake();
  }
  OFCondition renegotiate(const char* suite) override {
    return inner_->renegotiate(suite);
  }
  ssize_t read(void* buf, size_t nbyte) override {
    if (failed_) {
      errno = ECONNRESET;
      return -1;
    }
    if (replay_at_ < replay_.size()) {
      // Already fed to the guard by the gate.
      const size_t n = std::min(nbyte, replay_.size() - replay_at_);
      std::memcpy(buf, replay_.data() + replay_at_, n);
      replay_at_ += n;
      if (replay_at_ == replay_.size()) {
        replay_.clear();
        replay_.shrink_to_fit();
        replay_at_ = 0;
        AfterRequest();
      }
      return static_cast<ssize_t>(n);
    }
    const ssize_t r = inner_->read(buf, nbyte);
    if (r <= 0) return r;
    const bool was_in = guard_->in_pdu();
    const int64_t before = guard_->pdus();
    if (absl::Status s = guard_->Feed(static_cast<unsigned char*>(buf),
                                      static_cast<size_t>(r));
        !s.ok()) {
      failed_ = true;
      runner_->refusals->Refused(refusal::kProtocol, source_,
                                 std::string(s.message()));
      ::shutdown(getSocket(), SHUT_RDWR);
      errno = EPROTO;
      return -1;
    }
    if (watch_ != nullptr && guard_->request_complete()) {
      if (before == 0) {
        AfterRequest();
      } else if (!guard_->in_pdu()) {
        watch_->SetDeadline(0, nullptr);
      } else if (!was_in || guard_->pdus() != before) {
        // Slow senders: a PDU must arrive whole within pdu_timeout of its
        // first byte.
        watch_->SetDeadline(
            SteadyMillisNow() +
                static_cast<int64_t>(runner_->options.pdu_timeout_seconds *
                                     1000),
            refusal::kPduDeadline);
      }
    }
    return r;
  }
  ssize_t write(void* buf, size_t nbyte) override {
    return inner_->write(buf, nbyte);
  }
  void close() override {
    Unwatch();
    inner_->close();
  }
  void closeTransportConnection() override {
    inner_->closeTransportConnection();
  }
  unsigned long getPeerCertificateLength() override {
    return inner_->getPeerCertificateLength();
  }
  unsigned long getPeerCertificate(void* buf, unsigned long len) override {
    return inner_->getPeerCertificate(buf, len);
  }
  OFBool networkDataAvailable(int timeout) override {
    if (replay_at_ < replay_.size()) return OFTrue;
    return inner_->networkDataAvailable(timeout);
  }
  // Not transparent: DCMTK must ask networkDataAvailable() (which knows of
  // replayed bytes) instead of polling the socket itself.
  OFBool isTransparentConnection() override { return OFFalse; }
  OFString& dumpConnectionParameters(OFString& str) override {
    return inner_->dumpConnectionParameters(str);
  }

 private:
  // The request is in: no deadline until the next PDU begins.
  void AfterRequest() {
    if (watch_ != nullptr && guard_->request_complete() && !guard_->in_pdu()) {
      watch_->SetDeadline(0, nullptr);
    }
  }
  void Unwatch() {
    if (watch_ != nullptr && runner_->gate != nullptr) {
      runner_->gate->Unwatch(watch_);
    }
    watch_.reset();
  }

  DcmTransportConnection* const inner_;
  std::string replay_;
  size_t replay_at_ = 0;
  std::unique_ptr<PduGuard> guard_;
  std::shared_ptr<ConnectionWatch> watch_;
  const std::string source_;
  AssociationRunner::Impl* const runner_;
  bool failed_ = false;
};

// The network's transport layer: makes the connection object for the socket
// being handed over (plain or TLS), wrapped in a GuardedConnection.
class GuardedLayer : public DcmTransportLayer {
 public:
  explicit GuardedLayer(DcmTransportLayer* tls) : tls_(tls) {}
  DcmTransportConnection* createConnection(DcmNativeSocketType socket,
                                           OFBool secure) override {
    Handover& h = t_handover;
    if (h.connection == nullptr || h.connection->fd != socket) return nullptr;
    h.reached = true;
    dcmExternalSocketHandle.set(DCMNET_INVALID_SOCKET);
    if (h.lock != nullptr && h.lock->owns_lock()) h.lock->unlock();
    DcmTransportConnection* inner = nullptr;
    if (secure) {
      if (tls_ != nullptr) inner = tls_->createConnection(socket, OFTrue);
    } else {
      inner = new DcmTCPConnection(socket);
    }
    if (inner == nullptr) return nullptr;
    return new GuardedConnection(socket, inner, *h.connection, h.runner);
  }

 private:
  DcmTransportLayer* const tls_;
};

// One association: its AE titles, the series it stored into, and how it
// ended. DcmThreadSCP runs the DCMTK association state machine.
class AssociationScp : public DcmThreadSCP {
 public:
  AssociationScp(AssociationRunner::Impl* impl, std::string source,
                 std::function<void()> release_slot)
      : impl_(impl),
        source_(std::move(source)),
        release_slot_(std::move(release_slot)) {}
  ~AssociationScp() override {
    if (association_ != 0) {
      impl_->intake->EndTransfer(association_, false);
      EndMoves();
    }
  }

 protected:
  OFBool checkCalledAETitleAccepted(const OFString& called) override {
    const std::string ae = Trimmed(called.c_str());
    for (const std::string& ours : impl_->options.ae_titles) {
      if (ours == ae) return OFTrue;
    }
    rejection_ = refusal::kCalledAe;
    rejection_detail_ =
        absl::StrCat("called AE title ", LogSafe(ae), " is not served here");
    return OFFalse;
  }

  OFBool checkCallingAETitleAccepted(const OFString& calling) override {
    const std::string ae = Trimmed(calling.c_str());
    if (const char* bad = AeTitleFault(ae); bad != nullptr) {
      rejection_ = refusal::kCallingAe;
      rejection_detail_ = absl::StrCat("calling AE title ", bad);
      return OFFalse;
    }
    if (ae.empty()) {
      // PS3.8 9.3.2: an AE title is never all spaces. Refused here even
      // when unknown callers are accepted: DCMTK 3.6.7 cannot answer such
      // a request with an A-ASSOCIATE-AC (constructAssociatePDU refuses the
      // empty title and leaks the PDU's lists, 64 bytes per association),
      // so accepting it would only leak and abort.
      rejection_ = refusal::kCallingAe;
      rejection_detail_ = "calling AE title is empty";
      return OFFalse;
    }
    bool known = false;
    std::vector<std::string> allowed;
    const std::shared_ptr<const PeersConfig> peers = impl_->Peers();
    for (const DicomPeer& peer : peers->peers) {
      if (peer.ae_title != ae) continue;
      known = true;
      if (peer.allowed_sources.empty()) return OFTrue;
      for (const SourceNetwork& network : peer.allowed_sources) {
        if (InNetwork(source_, network)) return OFTrue;
        allowed.push_back(network.text);
      }
    }
    if (!known) {
      if (peers->accept_unknown_callers) return OFTrue;
      rejection_ = refusal::kCallingAe;
      rejection_detail_ = absl::StrCat("calling AE title ", LogSafe(ae),
                                       " is not in the peers file");
      return OFFalse;
    }
    rejection_ = refusal::kCallingAddress;
    rejection_detail_ =
        absl::StrCat("calling AE title ", LogSafe(ae),
                     " is not allowed from this address (its peer allows ",
                     absl::StrJoin(allowed, ", "), ")");
    return OFFalse;
  }

  void refuseAssociation(const DcmRefuseReasonType reason) override {
    const char* why = rejection_;
    std::string detail = rejection_detail_;
    if (reason == DCMSCP_NO_PRESENTATION_CONTEXTS) {
      why = refusal::kNoContext;
      detail =
          "no presentation context this node accepts was proposed (it "
          "serves Verification and the Storage classes of its conformance "
          "statement; C-FIND, C-MOVE and C-GET are not served)";
    } else if (why == nullptr) {
      why = refusal::kOtherRejection;
      detail = absl::StrCat("DCMTK refusal reason ", static_cast<int>(reason));
    }
    impl_->Count("associations_rejected");
    impl_->refusals->Refused(
        why, source_,
        absl::StrCat("association ", LogSafe(calling_), " -> ",
                     LogSafe(called_), " rejected: ", detail));
    DcmThreadSCP::refuseAssociation(reason);
  }

  void notifyAssociationRequest(const T_ASC_Parameters& params,
                                DcmSCPActionType& action) override {
    calling_ = Trimmed(params.DULparams.callingAPTitle);
    called_ = Trimmed(params.DULparams.calledAPTitle);
    params_ = &params;
  }

  void notifyAssociationAcknowledge() override {
    impl_->Count("associations");
    association_ = impl_->intake->BeginTransfer(node::Door::kAssociation,
                                                calling_, called_);
    auto* params = const_cast<T_ASC_Parameters*>(params_);
    const int refused = ASC_countPresentationContexts(params) -
                        ASC_countAcceptedPresentationContexts(params);
    if (refused > 0) {
      // E.g. getscu: its C-GET context is refused, its storage contexts
      // (for the sub-operations) accepted; it then gives up by itself.
      impl_->Count("presentation_contexts_refused", refused);
    }
    if (impl_->options.audit != nullptr) {
      AuditEvent e;
      e.event = "association.accepted";
      e.identity = absl::StrCat("dicom:", calling_, "->", called_);
      e.source = source_;
      impl_->options.audit->Record(std::move(e));
    }
    spdlog::info(
        "dicom: association {} -> {} from {} accepted{}", LogSafe(calling_),
        LogSafe(called_), LogSafe(source_),
        refused > 0
            ? absl::StrCat(" (", refused,
                           " proposed presentation context(s) refused: not "
                           "served here, e.g. C-FIND, C-MOVE, C-GET)")
            : "");
  }

  // The association's end begins: its place in the per-source count is
  // free before the release is acknowledged (the sender may associate again
  // the moment it reads the answer).
  void notifyReleaseRequest() override {
    released_ = true;
    FreeSlot();
  }
  void notifyAbortRequest() override { FreeSlot(); }
  void FreeSlot() {
    if (release_slot_) release_slot_();
  }

  // Called while a data set streams in: the bytes so far. An instance
  // larger than a whole series may be is cut off here, by aborting the
  // association, instead of being written to the end first.
  void notifyRECEIVEProgress(const unsigned long bytes) override {
    received_ = static_cast<int64_t>(bytes);
    if (receiving_ && !cut_off_ && received_ > allowance_) {
      cut_off_ = true;
      spdlog::warn(
          "dicom: association {} -> {} aborted: an instance passed {} bytes, "
          "the limit per series",
          LogSafe(calling_), LogSafe(called_), allowance_);
      abortAssociation();
    }
  }

  void notifyAssociationTermination() override {
    if (association_ == 0) return;
    const bool clean = released_ && !cut_off_;
    impl_->intake->EndTransfer(association_, clean);
    EndMoves();
    association_ = 0;
    if (impl_->options.audit != nullptr) {
      AuditEvent e;
      e.event = "association.ended";
      e.outcome = clean && refused_ == 0 ? AuditOutcome::kSuccess
                                         : AuditOutcome::kMinorFailure;
      e.identity = absl::StrCat("dicom:", calling_, "->", called_);
      e.source = source_;
      e.count = stored_;
      e.detail = absl::StrCat(clean ? "released" : "aborted", ": ", stored_,
                              " instance(s) kept, ", refused_, " refused");
      impl_->options.audit->Record(std::move(e));
    }
    spdlog::info(
        "dicom: association {} -> {} {}: {} instance(s) kept, {} refused",
        LogSafe(calling_), LogSafe(called_), clean ? "released" : "aborted",
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
  OFCondition Refuse(Uint16 status, T_DIMSE_C_StoreRQ& request,
                     const DcmPresentationContextInfo& info) {
    ++refused_;
    impl_->Count("instances_refused");
    return sendSTOREResponse(info.presentationContextID, request, status);
  }

  OFCondition HandleStore(T_DIMSE_C_StoreRQ& request,
                          const DcmPresentationContextInfo& info) {
    const std::string staged = impl_->intake->StagingPath();
    allowance_ = impl_->intake->max_instance_bytes();
    received_ = 0;
    receiving_ = true;
    // Written as received: DCMTK writes the meta group and then the data
    // set's bytes, unparsed.
    OFCondition cond = receiveSTORERequest(request, info.presentationContextID,
                                           OFString(staged.c_str()));
    receiving_ = false;
    if (cut_off_ && cond.good()) cond = DUL_PEERABORTEDASSOCIATION;
    if (cond.bad()) {
      ::unlink(staged.c_str());
      if (!cut_off_ && cond.module() == OFM_dcmnet &&
          cond.code() == DIMSEC_OUTOFRESOURCES) {
        // The file could not be created or written (a full disk): DCMTK
        // read the rest of the data set and dropped it, so the association
        // goes on and the instance is refused as PS3.4 B.2.3 says.
        spdlog::warn(
            "dicom: instance from {} refused (out of resources): the disk "
            "is full",
            LogSafe(calling_));
        impl_->intake->InstanceRefused(association_);
        return Refuse(STATUS_STORE_Refused_OutOfResources, request, info);
      }
      // The association ends (DcmSCP aborts it); nothing was acknowledged.
      spdlog::warn("dicom: receiving an instance from {} failed: {}",
                   LogSafe(calling_), LogSafe(cond.text()));
      return cond;
    }
    if (info.abstractSyntax != request.AffectedSOPClassUID) {
      ::unlink(staged.c_str());
      impl_->intake->InstanceRefused(association_);
      return Refuse(STATUS_STORE_Error_DataSetDoesNotMatchSOPClass, request,
                    info);
    }
    // An instance of a C-MOVE of ours goes to the move's folder, never to
    // the assembler and the rules (pending_moves.h). Its UIDs are read (after
    // the bounded scan) only when its caller has a move pending.
    PendingMoves* moves = impl_->options.pending_moves;
    if (moves != nullptr && moves->Expects(calling_)) {
      absl::StatusOr<ReceivedInstance> received =
          ReadReceivedInstance(staged, received_, impl_->intake->scan_limits());
      if (received.ok()) {
        std::shared_ptr<PendingMoves::Move> move = moves->Find(
            calling_, received->ids.study_uid, received->ids.series_uid);
        // Once its move has ended, only an instance that says it is one of
        // our C-MOVE's sub-operations belongs to it (a late one, refused);
        // a push of the same series is an ordinary transfer.
        if (move != nullptr && (!move->ended() || SaysOurMove(request))) {
          return StoreForMove(std::move(move), staged, received->size, request,
                              info);
        }
      }
      // Not a moved instance (or unreadable: the assembler refuses it with
      // the same reason).
    }
    absl::StatusOr<std::string> key =
        impl_->intake->AddInstance(association_, staged, received_);
    if (key.ok()) {
      ++stored_;
      impl_->Count("instances_received");
      return sendSTOREResponse(info.presentationContextID, request,
                               STATUS_Success);
    }
    const uint16_t status = node::StoreStatusOfRefusal(key.status());
    spdlog::warn("dicom: instance from {} refused ({}): {}", LogSafe(calling_),
                 node::CStoreStatusText(status),
                 LogSafe(key.status().message()));
    return Refuse(status, request, info);
  }

  // The C-STORE request names a C-MOVE of ours as its origin: its Move
  // Originator AE Title (PS3.7 9.1.1.1) is one of the AE titles we call as
  // (our C-MOVEs call as the first).
  bool SaysOurMove(const T_DIMSE_C_StoreRQ& request) const {
    if ((request.opts & O_STORE_MOVEORIGINATORAETITLE) == 0) return false;
    const std::string originator(absl::StripAsciiWhitespace(
        request.MoveOriginatorApplicationEntityTitle));
    const std::vector<std::string>& ours = impl_->options.ae_titles;
    return std::find(ours.begin(), ours.end(), originator) != ours.end();
  }

  OFCondition StoreForMove(std::shared_ptr<PendingMoves::Move> move,
                           const std::string& staged, int64_t size,
                           T_DIMSE_C_StoreRQ& request,
                           const DcmPresentationContextInfo& info) {
    if (std::find(moves_.begin(), moves_.end(), move) == moves_.end()) {
      moves_.push_back(move);
    }
    const absl::Status kept = move->Accept(association_, staged, size);
    if (kept.ok()) {
      ++stored_;
      impl_->Count("instances_moved");
      return sendSTOREResponse(info.presentationContextID, request,
                               STATUS_Success);
    }
    spdlog::warn("dicom: instance of a C-MOVE from {} refused: {}",
                 LogSafe(calling_), LogSafe(kept.message()));
    return Refuse(node::StoreStatusOfRefusal(kept), request, info);
  }

  // The association ends: the moves it stored into stop waiting for it.
  void EndMoves() {
    for (const std::shared_ptr<PendingMoves::Move>& move : moves_) {
      move->AssociationEnded(association_);
    }
    moves_.clear();
  }

  AssociationRunner::Impl* const impl_;
  const std::string source_;
  const std::function<void()> release_slot_;
  std::vector<std::shared_ptr<PendingMoves::Move>> moves_;
  std::string calling_, called_;
  const T_ASC_Parameters* params_ = nullptr;
  const char* rejection_ = nullptr;
  std::string rejection_detail_;
  uint64_t association_ = 0;
  int64_t stored_ = 0, refused_ = 0;
  bool released_ = false;
  bool receiving_ = false;
  bool cut_off_ = false;
  int64_t allowance_ = 0;
  int64_t received_ = 0;
};

}  // namespace

void AssociationRunner::SetPeers(PeersConfig peers) {
  auto next = std::make_shared<const PeersConfig>(std::move(peers));
  std::lock_guard<std::mutex> lock(impl_->peers_mu);
  impl_->peers = std::move(next);
}

absl::StatusOr<std::unique_ptr<AssociationRunner>> AssociationRunner::Create(
    const StorageScpOptions& options, node::Intake* intake, Metrics* metrics,
    RefusalLog* refusals, ConnectionGate* gate) {
  std::unique_ptr<AssociationRunner> runner(new AssociationRunner());
  runner->impl_ = std::make_unique<Impl>();
  Impl& impl = *runner->impl_;
  impl.options = options;
  impl.peers = std::make_shared<const PeersConfig>(options.peers);
  impl.intake = intake;
  impl.metrics = metrics;
  impl.refusals = refusals;
  impl.gate = gate;
  if (!options.tls.certificate.empty() || !options.tls.private_key.empty() ||
      !options.tls.ca_certificates.empty()) {
    absl::StatusOr<DicomTlsLayer> tls =
        MakeDicomTls(options.tls, /*server_role=*/true);
    if (!tls.ok()) return tls.status();
    impl.tls = *std::move(tls);
  }
  impl.layer = std::make_unique<GuardedLayer>(impl.tls.get());

  DcmSCPConfig& cfg = *impl.config;
  cfg.setAETitle(options.ae_titles.front().c_str());
  // Several called AE titles: answer with the one that was called
  // (checkCalledAETitleAccepted decides which are served).
  cfg.setRespondWithCalledAETitle(OFTrue);
  cfg.setMaxReceivePDULength(options.max_pdu_bytes);
  cfg.setDIMSEBlockingMode(DIMSE_NONBLOCKING);
  cfg.setDIMSETimeout(
      static_cast<Uint32>(std::max(1.0, options.dimse_timeout_seconds)));
  cfg.setACSETimeout(
      static_cast<Uint32>(std::max(1.0, options.acse_timeout_seconds)));
  cfg.setHostLookupEnabled(OFFalse);
  cfg.setProgressNotificationMode(OFTrue);
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
  for (const std::string& sop : node::StorableSopClasses()) {
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

  // An acceptor network without a listening socket of its own (the gate
  // listens): DUL skips creating one while an external socket is set.
  {
    std::lock_guard<std::mutex> lock(g_external_socket_mu);
    dcmExternalSocketHandle.set(0);
    cond = ASC_initializeNetwork(
        NET_ACCEPTOR, 0,
        static_cast<int>(std::max(1.0, options.acse_timeout_seconds)),
        &impl.network);
    dcmExternalSocketHandle.set(DCMNET_INVALID_SOCKET);
  }
  if (cond.bad()) {
    return absl::InternalError(
        absl::StrCat("DICOM listener set-up: ", cond.text()));
  }
  cond = ASC_setTransportLayer(impl.network, impl.layer.get(), 0);
  if (cond.bad()) {
    return absl::InternalError(
        absl::StrCat("DICOM listener set-up: ", cond.text()));
  }
  return runner;
}

AssociationRunner::~AssociationRunner() {
  if (impl_ && impl_->network != nullptr) ASC_dropNetwork(&impl_->network);
}

void AssociationRunner::Serve(ReadyConnection connection) {
  Impl& impl = *impl_;
  const int fd = connection.fd;
  std::shared_ptr<ConnectionWatch> watch = connection.watch;
  const std::string source = connection.source;
  T_ASC_Association* assoc = nullptr;
  OFCondition cond;
  bool reached = false;
  {
    std::unique_lock<std::mutex> lock(g_external_socket_mu);
    dcmExternalSocketHandle.set(fd);
    t_handover = Handover{&connection, &lock, &impl, false};
    cond = ASC_receiveAssociation(
        impl.network, &assoc, static_cast<int>(impl.options.max_pdu_bytes),
        nullptr, nullptr, impl.tls ? OFTrue : OFFalse, DUL_BLOCK, 0);
    reached = t_handover.reached;
    t_handover = Handover{};
    if (lock.owns_lock()) dcmExternalSocketHandle.set(DCMNET_INVALID_SOCKET);
  }
  if (!reached) {
    // DCMTK failed before it took the socket (the peer left already).
    if (impl.gate != nullptr) impl.gate->Unwatch(watch);
    ::close(fd);
  }
  if (cond.bad()) {
    // The request never arrived whole: the guard, a deadline or the TLS
    // handshake said why (and counted it); or the peer closed.
    if (assoc != nullptr) {
      ASC_dropAssociation(assoc);
      ASC_destroyAssociation(&assoc);
    }
    return;
  }
  AssociationScp scp(&impl, source, connection.release_slot);
  scp.setSharedConfig(impl.config);
  // Negotiation (our checks are called back), then the DIMSE loop; the
  // association is dropped when `scp` goes.
  scp.run(assoc);
}

}  // namespace interslice::server::dimse
