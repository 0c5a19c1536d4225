#include "server/net/dicomweb/stow.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <memory>
#include <optional>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "nlohmann/json.hpp"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "server/engine/spool.h"
#include "server/net/dicomweb/multipart.h"
#include "server/node/dataset_scan.h"
#include "server/node/intake.h"
#include "server/node/outcome.h"
#include "server/node/received_instance.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dicomweb {
namespace {

struct PartOutcome {
  std::string sop_class, sop_instance;
  int failure = 0;    // 0: stored (when done)
  bool done = false;  // the part ended (a cut-off body leaves one open)
};

std::string GetString(DcmItem* item, const DcmTagKey& tag) {
  OFString value;
  if (item->findAndGetOFStringArray(tag, value).good()) return value.c_str();
  return "";
}

// Writes each application/dicom part to a staging file and hands it to the
// assembler when it ends (the MultipartSink of multipart.h).
class StagingSink : public MultipartSink {
 public:
  StagingSink(node::Intake* assembler, Spool* spool, uint64_t association,
              std::string fallback_type, std::string study_uid)
      : assembler_(assembler),
        spool_(spool),
        association_(association),
        fallback_type_(std::move(fallback_type)),
        study_uid_(std::move(study_uid)) {}
  ~StagingSink() override { Discard(); }

  absl::Status BeginPart(const PartHeaders& headers) override {
    outcomes_.emplace_back();
    if (PartMediaType(headers, fallback_type_) != "application/dicom") {
      Refuse(kFailureCannotUnderstand, "a part is not application/dicom");
      return absl::OkStatus();
    }
    staged_ = assembler_->StagingPath();
    fd_ =
        ::open(staged_.c_str(), O_CREAT | O_EXCL | O_WRONLY | O_CLOEXEC, 0600);
    if (fd_ < 0) {
      staged_.clear();
      Refuse(kFailureOutOfResources, "cannot create a staging file");
    }
    size_ = 0;
    return absl::OkStatus();
  }

  absl::Status PartBytes(std::string_view bytes) override {
    if (fd_ < 0) return absl::OkStatus();  // refused: its bytes are dropped
    size_ += static_cast<int64_t>(bytes.size());
    if (size_ > assembler_->max_instance_bytes()) {
      Discard();
      Refuse(kFailureOutOfResources,
             "an instance is larger than a series may be");
      return absl::OkStatus();
    }
    while (!bytes.empty()) {
      const ssize_t n = ::write(fd_, bytes.data(), bytes.size());
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        Discard();
        Refuse(kFailureOutOfResources, "the disk is full");
        return absl::OkStatus();
      }
      bytes.remove_prefix(static_cast<size_t>(n));
    }
    return absl::OkStatus();
  }

  absl::Status EndPart() override {
    outcomes_.back().done = true;
    if (fd_ < 0) return absl::OkStatus();
    const bool closed = ::close(fd_) == 0;
    fd_ = -1;
    if (!closed) {
      Discard();
      Refuse(kFailureOutOfResources, "the disk is full");
      return absl::OkStatus();
    }
    PartOutcome& outcome = outcomes_.back();
    // Bounded first: DCMTK parses only what the scan passed.
    if (absl::StatusOr<node::DatasetScanResult> scan =
            node::ScanPart10File(staged_);
        !scan.ok()) {
      Discard();
      Refuse(kFailureCannotUnderstand, std::string(scan.status().message()));
      return absl::OkStatus();
    }
    std::string study;
    {
      DcmFileFormat file;
      if (file.loadFileUntilTag(staged_.c_str(), EXS_Unknown, EGL_noChange,
                                DCM_MaxReadLength, ERM_fileOnly, DCM_PixelData)
              .bad()) {
        Discard();
        Refuse(kFailureCannotUnderstand, "not readable DICOM");
        return absl::OkStatus();
      }
      DcmDataset* ds = file.getDataset();
      outcome.sop_class = GetString(ds, DCM_SOPClassUID);
      outcome.sop_instance = GetString(ds, DCM_SOPInstanceUID);
      study = GetString(ds, DCM_StudyInstanceUID);
    }
    if (!study_uid_.empty() && study != study_uid_) {
      Discard();
      Refuse(kFailureDoesNotMatch,
             "an instance of another study than the request's");
      return absl::OkStatus();
    }
    // The quota refusal is told apart (-> 507) before the assembler's own
    // reservation (which stays the one that counts).
    if (spool_ != nullptr &&
        spool_->used_bytes() + size_ > spool_->quota_bytes()) {
      Discard();
      quota_refused_ = true;
      Refuse(kFailureOutOfResources, "the spool quota is reached");
      return absl::OkStatus();
    }
    const std::string staged = std::exchange(staged_, std::string());
    absl::StatusOr<std::string> key =
        assembler_->AddInstance(association_, staged, -1);  // deletes staged
    if (key.ok()) {
      ++stored_;
      return absl::OkStatus();
    }
    // AddInstance already marked what the instance belonged to.
    outcome.failure = node::StoreStatusOfRefusal(key.status());
    ++failed_;
    last_reason_ = std::string(key.status().message());
    return absl::OkStatus();
  }

  const std::vector<PartOutcome>& outcomes() const { return outcomes_; }
  int64_t failed() const { return failed_; }
  int64_t stored() const { return stored_; }
  bool quota_refused() const { return quota_refused_; }
  const std::string& last_reason() const { return last_reason_; }

  // The part in progress when the body stopped (not confirmed): dropped.
  void Discard() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    if (!staged_.empty()) ::unlink(staged_.c_str());
    staged_.clear();
  }

 private:
  // The current part is refused before the assembler saw it: every series
  // of the association misses an instance.
  void Refuse(int reason, std::string_view why) {
    PartOutcome& outcome = outcomes_.back();
    if (outcome.failure != 0) return;
    outcome.failure = reason;
    ++failed_;
    last_reason_ = std::string(why);
    assembler_->InstanceRefused(association_);
  }

  node::Intake* const assembler_;
  Spool* const spool_;
  const uint64_t association_;
  const std::string fallback_type_;
  const std::string study_uid_;
  std::vector<PartOutcome> outcomes_;
  std::string staged_;
  int fd_ = -1;
  int64_t size_ = 0;
  int64_t failed_ = 0, stored_ = 0;
  bool quota_refused_ = false;
  std::string last_reason_;
};

StowResponse Plain(int status, std::string text) {
  StowResponse r;
  r.status = status;
  r.body = std::move(text) + "\n";
  return r;
}

nlohmann::json Uid(const std::string& uid) {
  nlohmann::json j = {{"vr", "UI"}};
  if (!uid.empty()) j["Value"] = {uid};
  return j;
}

// PS3.18 10.5.3 Store Instances Response Module, as DICOM JSON (Annex F).
std::string ResponseJson(const std::vector<PartOutcome>& outcomes) {
  nlohmann::json referenced = nlohmann::json::array();
  nlohmann::json failed = nlohmann::json::array();
  for (const PartOutcome& o : outcomes) {
    nlohmann::json item = {{"00081150", Uid(o.sop_class)},
                           {"00081155", Uid(o.sop_instance)}};
    if (o.failure == 0) {
      referenced.push_back(std::move(item));
    } else {
      item["00081197"] = {{"vr", "US"}, {"Value", {o.failure}}};
      failed.push_back(std::move(item));
    }
  }
  nlohmann::json body = nlohmann::json::object();
  if (!failed.empty()) body["00081198"] = {{"vr", "SQ"}, {"Value", failed}};
  if (!referenced.empty()) {
    body["00081199"] = {{"vr", "SQ"}, {"Value", referenced}};
  }
  return body.dump() + "\n";
}

}  // namespace

std::optional<std::string> StowStudyOfPath(std::string_view path) {
  constexpr std::string_view kStudies = "/dicomweb/studies";
  if (path == kStudies) return std::string();
  if (path.size() > kStudies.size() + 1 &&
      path.substr(0, kStudies.size() + 1) == "/dicomweb/studies/") {
    const std::string_view study = path.substr(kStudies.size() + 1);
    if (IsUidPathSegment(study)) return std::string(study);
  }
  return std::nullopt;
}

bool IsUidPathSegment(std::string_view uid) {
  if (uid.empty() || uid.size() > 64) return false;
  // Components are non-empty runs of digits between dots.
  bool empty_component = true;
  for (const char c : uid) {
    if (c == '.') {
      if (empty_component) return false;
      empty_component = true;
    } else if (c >= '0' && c <= '9') {
      empty_component = false;
    } else {
      return false;
    }
  }
  return !empty_component;
}

std::optional<HttpServerResponse> StowReceiver::Screen(
    std::string_view method, std::string_view path) const {
  if (!StowStudyOfPath(path).has_value()) {
    return HttpServerResponse{
        .status = 404,
        .body =
            "not found: STOW-RS is POST /dicomweb/studies or "
            "/dicomweb/studies/{StudyInstanceUID}\n"};
  }
  if (method != "POST") {
    return HttpServerResponse{.status = 405,
                              .body = "STOW-RS takes POST only\n",
                              .extra_headers = "Allow: POST\r\n"};
  }
  return std::nullopt;
}

HttpServerResponse StowReceiver::Serve(const HttpServerRequest& request) const {
  if (request.identity.empty() && options_.refuse_anonymous) {
    return {.status = 403,
            .body =
                "this server authenticates by client certificate, which "
                "its HTTP listener does not check: STOW-RS needs a token "
                "(--auth-token-file)\n"};
  }
  const StowResponse response =
      Handle({.identity = request.identity,
              .source = request.source,
              .content_type = request.header("Content-Type"),
              .study_uid = StowStudyOfPath(request.path).value_or(""),
              .content_length = request.content_length,
              .read = request.read});
  return {.status = response.status,
          .content_type = response.content_type,
          .body = response.body};
}

StowReceiver::StowReceiver(StowOptions options, node::Intake* assembler,
                           Spool* spool, AuditLog* audit)
    : options_(std::move(options)),
      assembler_(assembler),
      spool_(spool),
      audit_(audit),
      max_body_bytes_(options_.max_body_bytes > 0
                          ? options_.max_body_bytes
                          : assembler->max_instance_bytes()) {}

StowResponse StowReceiver::Handle(const StowRequest& request) const {
  const std::string identity =
      request.identity.empty() ? "STOW" : "STOW:" + request.identity;
  auto audit = [&](const StowResponse& r, const std::string& detail) {
    if (audit_ == nullptr) return;
    audit_->Record({.event = "stow.received",
                    .outcome = r.status == 200 ? AuditOutcome::kSuccess
                               : r.stored > 0  ? AuditOutcome::kMinorFailure
                                               : AuditOutcome::kSeriousFailure,
                    .identity = identity,
                    .source = request.source,
                    .count = r.stored,
                    .detail = absl::StrCat("HTTP ", r.status, ": ", detail)});
  };
  auto refuse_early = [&](int status, std::string text) {
    StowResponse r = Plain(status, std::move(text));
    audit(r, r.body.substr(0, r.body.size() - 1));
    spdlog::warn("dicomweb: STOW from {} refused ({}): {}", LogSafe(identity),
                 status, LogSafe(r.body.substr(0, r.body.size() - 1)));
    return r;
  };

  absl::StatusOr<StowContentType> type =
      ParseStowContentType(request.content_type);
  if (!type.ok()) {
    return refuse_early(
        type.status().code() == absl::StatusCode::kUnimplemented ? 415 : 400,
        std::string(type.status().message()));
  }
  if (request.content_length > max_body_bytes_) {
    return refuse_early(413,
                        absl::StrCat("the body (", request.content_length,
                                     " bytes) is larger than the limit of ",
                                     max_body_bytes_, " bytes per request"));
  }
  if (spool_ != nullptr && (spool_->used_bytes() >= spool_->quota_bytes() ||
                            (request.content_length > 0 &&
                             spool_->used_bytes() + request.content_length >
                                 spool_->quota_bytes()))) {
    return refuse_early(507,
                        "the spool quota has no room for this body: try again "
                        "later");
  }

  const uint64_t association = assembler_->BeginTransfer(
      node::Door::kStowRequest, identity, options_.called_ae);
  StagingSink sink(assembler_, spool_, association, type->type,
                   request.study_uid);
  // A multipart body goes through the parser; a single-part body (Content-
  // Type application/dicom) is one part, its bytes the instance.
  std::unique_ptr<MultipartParser> parser;
  if (!type->single_part) {
    parser = std::make_unique<MultipartParser>(type->boundary,
                                               StowRequestMultipart(), &sink);
  }
  bool single_part_begun = false;
  auto feed = [&](std::string_view bytes) -> absl::Status {
    if (parser != nullptr) return parser->Feed(bytes);
    if (!single_part_begun) {
      single_part_begun = true;
      if (absl::Status s = sink.BeginPart({}); !s.ok()) return s;
    }
    return sink.PartBytes(bytes);
  };
  auto finish = [&]() -> absl::Status {
    if (parser != nullptr) return parser->Finish();
    return single_part_begun ? sink.EndPart() : absl::OkStatus();
  };
  std::vector<char> buffer(options_.read_chunk_bytes);
  int64_t total = 0;
  absl::Status parsed = absl::OkStatus();
  bool too_large = false, cut = false;
  while (true) {
    const int64_t n = request.read(buffer.data(), buffer.size());
    if (n < 0) {
      cut = true;
      break;
    }
    if (n == 0) break;
    total += n;
    if (total > max_body_bytes_) {
      too_large = true;
      break;
    }
    parsed = feed(std::string_view(buffer.data(), static_cast<size_t>(n)));
    if (!parsed.ok()) break;
  }
  // The body ended before the bytes its Content-Length promised (issue 39,
  // finding 2: the client still waiting when the server's read timed out):
  // whatever the parser made of it, the request did not arrive whole.
  const bool short_body = !cut && !too_large && parsed.ok() &&
                          request.content_length >= 0 &&
                          total < request.content_length;
  if (short_body) cut = true;
  if (parsed.ok() && !too_large && !cut) parsed = finish();
  sink.Discard();
  StowResponse r;
  r.failed = sink.failed();
  r.stored = sink.stored();
  r.released = parsed.ok() && !too_large && !cut && sink.failed() == 0;
  assembler_->EndTransfer(association, r.released);

  if (options_.metrics != nullptr) {
    options_.metrics->StowBodyBytes(static_cast<double>(total));
    options_.metrics->StowInstances("stored", static_cast<double>(r.stored));
    options_.metrics->StowInstances("refused", static_cast<double>(r.failed));
  }
  std::string detail =
      absl::StrCat(r.stored, " instance(s) kept, ", r.failed, " refused");
  if (too_large) {
    r.status = 413;
    r.body = absl::StrCat("the body passed the limit of ", max_body_bytes_,
                          " bytes per request; what arrived is incomplete\n");
  } else if (short_body) {
    r.status = 400;
    r.body = absl::StrCat("the body ended after ", total, " of the ",
                          request.content_length,
                          " bytes its Content-Length promised; what arrived "
                          "is incomplete\n");
  } else if (cut) {
    r.status = 400;
    r.body = "the body did not arrive whole (timeout or connection lost)\n";
  } else if (!parsed.ok()) {
    r.status = 400;
    r.body = absl::StrCat(parsed.message(), "\n");
  } else if (sink.outcomes().empty()) {
    r.status = 400;
    r.body = "the body holds no part\n";
  } else {
    r.status = r.failed == 0          ? 200
               : r.stored > 0         ? 202
               : sink.quota_refused() ? 507
                                      : 409;
    r.content_type = "application/dicom+json";
    r.body = ResponseJson(sink.outcomes());
  }
  if (r.status >= 400 && r.content_type == "text/plain") {
    absl::StrAppend(&detail, "; ", r.body.substr(0, r.body.size() - 1));
  } else if (r.failed > 0) {
    absl::StrAppend(&detail, "; last refusal: ", sink.last_reason());
  }
  absl::StrAppend(&detail, r.released ? "; complete" : "; not complete");
  audit(r, detail);
  spdlog::info("dicomweb: STOW {} -> {} from {}: HTTP {}, {}",
               LogSafe(identity), LogSafe(options_.called_ae),
               LogSafe(request.source), r.status, LogSafe(detail));
  return r;
}

}  // namespace interslice::server::dicomweb
