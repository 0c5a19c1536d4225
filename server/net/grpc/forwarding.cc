#include "server/net/grpc/forwarding.h"

#include <cstdint>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "grpcpp/create_channel.h"
#include "grpcpp/support/channel_arguments.h"
#include "server/base/log_safe.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

constexpr char kBase32[] = "abcdefghijklmnopqrstuvwxyz234567";
constexpr size_t kLocalIdLength = 16;
constexpr size_t kMaxOwnerLength = 255;

std::string Base32Encode(std::string_view bytes) {
  std::string out;
  uint32_t buffer = 0;
  int bits = 0;
  for (unsigned char c : bytes) {
    buffer = (buffer << 8) | c;
    bits += 8;
    while (bits >= 5) {
      out.push_back(kBase32[(buffer >> (bits - 5)) & 31]);
      bits -= 5;
    }
  }
  if (bits > 0) out.push_back(kBase32[(buffer << (5 - bits)) & 31]);
  return out;
}

std::optional<std::string> Base32Decode(std::string_view text) {
  std::string out;
  uint32_t buffer = 0;
  int bits = 0;
  for (char c : text) {
    int v;
    if (c >= 'a' && c <= 'z') {
      v = c - 'a';
    } else if (c >= '2' && c <= '7') {
      v = c - '2' + 26;
    } else {
      return std::nullopt;
    }
    buffer = (buffer << 5) | static_cast<uint32_t>(v);
    bits += 5;
    if (bits >= 8) {
      out.push_back(static_cast<char>((buffer >> (bits - 8)) & 0xff));
      bits -= 8;
    }
  }
  // Canonical encodings only: the leftover bits are zero padding.
  if (bits >= 5 || (buffer & ((1u << bits) - 1)) != 0) return std::nullopt;
  return out;
}

struct HostPort {
  std::string host;
  bool ip_literal = false;
};

// HOST:PORT with a DNS name, an IPv4 address or a bracketed IPv6 address.
std::optional<HostPort> ParseHostPort(std::string_view address) {
  const size_t colon = address.rfind(':');
  if (colon == std::string_view::npos || colon == 0) return std::nullopt;
  int port = 0;
  if (!absl::SimpleAtoi(std::string(address.substr(colon + 1)), &port) ||
      port < 1 || port > 65535) {
    return std::nullopt;
  }
  std::string_view host = address.substr(0, colon);
  HostPort result;
  if (host.front() == '[') {
    if (host.size() < 3 || host.back() != ']') return std::nullopt;
    for (char c : host.substr(1, host.size() - 2)) {
      if (!absl::ascii_isxdigit(c) && c != ':' && c != '.') return std::nullopt;
    }
    result.ip_literal = true;
  } else {
    bool all_digits_and_dots = true;
    for (char c : host) {
      if (!absl::ascii_isalnum(c) && c != '.' && c != '-') return std::nullopt;
      if (!absl::ascii_isdigit(c) && c != '.') all_digits_and_dots = false;
    }
    result.ip_literal = all_digits_and_dots;
  }
  result.host = absl::AsciiStrToLower(std::string(host));
  return result;
}

grpc::Status OwnerStatus(const grpc::Status& status, const std::string& owner) {
  if (status.error_code() != grpc::UNAVAILABLE) return status;
  return grpc::Status(
      grpc::UNAVAILABLE,
      absl::StrCat("the replica ", owner,
                   " that holds this job is unavailable (",
                   status.error_message(),
                   "); the job is kept in its spool and returns with it"));
}

// Relays a server-streaming call to the owner: one message in flight, read
// from the owner only when the caller has taken the previous one. State
// changes under mu_; gRPC operations are started after releasing it, so a
// callback that gRPC runs at once cannot deadlock. The server reactor is the
// last of the pair to finish (it finishes only once the owner's call is
// done), so its OnDone deletes the pair.
//
// Lifetime of the owner's call: reads are started from the caller's
// OnWriteDone, outside the upstream reactor's own reactions, so the upstream
// call holds a hold (ClientReadReactor::AddHold) from before StartCall until
// we know no read will follow: a read came back !ok (the owner's stream
// ended) or a write to the caller failed (it went away). Without the hold the
// owner's status could arrive between two reads, gRPC would finish and free
// the upstream call, and the next StartRead would call into freed memory
// (the "pure virtual method called" abort, regression test
// ForwardedStreamTest.OwnerStoppingAtAnyMomentEndsTheCallCleanly). Exactly
// one of "a read outstanding" and "a write in flight" is true at any time,
// so the hold is removed exactly once.
template <typename Request, typename Response>
class ForwardedStream : public grpc::ServerWriteReactor<Response> {
 public:
  using Starter = void (v1::InterSlice::StubInterface::async_interface::*)(
      grpc::ClientContext*, const Request*, grpc::ClientReadReactor<Response>*);

  ForwardedStream(std::unique_ptr<grpc::ClientContext> client_context,
                  const Request& request, std::string owner,
                  v1::InterSlice::Stub* stub, Starter start)
      : client_context_(std::move(client_context)),
        request_(request),
        owner_(std::move(owner)),
        upstream_(this) {
    (stub->async()->*start)(client_context_.get(), &request_, &upstream_);
    upstream_.AddHold();
    upstream_.StartRead(&message_);
    upstream_.StartCall();
  }

  void OnWriteDone(bool ok) override {
    bool read = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      write_in_flight_ = false;
      if (!ok) {
        caller_gone_ = true;
      } else {
        read = !upstream_done_;
      }
    }
    if (!ok) {
      // No read is outstanding and none will be started: let the owner's
      // call finish (OnUpstreamDone follows).
      client_context_->TryCancel();
      upstream_.RemoveHold();
      return;
    }
    if (read) {
      upstream_.StartRead(&message_);  // safe: the hold keeps the call alive
    } else {
      MaybeFinish();
    }
  }
  void OnCancel() override { client_context_->TryCancel(); }
  void OnDone() override {
    // The owner's call may still be unlocking mu_ after its Finish().
    { std::lock_guard<std::mutex> lock(mu_); }
    delete this;
  }

 private:
  class Upstream : public grpc::ClientReadReactor<Response> {
   public:
    explicit Upstream(ForwardedStream* outer) : outer_(outer) {}
    void OnReadDone(bool ok) override { outer_->OnUpstreamRead(ok); }
    void OnDone(const grpc::Status& status) override {
      outer_->OnUpstreamDone(status);
    }

   private:
    ForwardedStream* const outer_;
  };

  void OnUpstreamRead(bool ok) {
    if (!ok) {
      // The owner's stream ended; no read will follow, so the call may
      // finish (OnUpstreamDone follows).
      upstream_.RemoveHold();
      return;
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      write_in_flight_ = true;
    }
    this->StartWrite(&message_);
  }
  void OnUpstreamDone(const grpc::Status& status) {
    if (status.error_code() == grpc::UNAVAILABLE) {
      spdlog::warn("forwarding to {}: the job's replica is unavailable",
                   LogSafe(owner_));
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      upstream_done_ = true;
      status_ = caller_gone_
                    ? grpc::Status(grpc::CANCELLED, "the client went away")
                    : OwnerStatus(status, owner_);
    }
    MaybeFinish();
  }
  // Finishes once both the owner's call and the last write are done.
  void MaybeFinish() {
    grpc::Status status;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (finished_ || write_in_flight_ || !upstream_done_) return;
      finished_ = true;
      status = status_;
    }
    this->Finish(status);
  }

  std::unique_ptr<grpc::ClientContext> client_context_;
  const Request request_;
  const std::string owner_;
  Upstream upstream_;
  std::mutex mu_;
  Response message_;
  grpc::Status status_;
  bool write_in_flight_ = false;
  bool upstream_done_ = false;
  bool caller_gone_ = false;
  bool finished_ = false;
};

}  // namespace

std::string JobIdSuffix(std::string_view advertise) {
  return absl::StrCat(".", Base32Encode(advertise));
}

std::optional<std::string> JobOwner(std::string_view job_id) {
  const size_t dot = job_id.find('.');
  if (dot != kLocalIdLength) return std::nullopt;
  std::optional<std::string> owner = Base32Decode(job_id.substr(dot + 1));
  if (!owner || owner->empty() || owner->size() > kMaxOwnerLength ||
      !ParseHostPort(*owner)) {
    return std::nullopt;
  }
  return owner;
}

bool IsReplicaAddress(std::string_view address) {
  return address.size() <= kMaxOwnerLength && ParseHostPort(address);
}

bool SameReplicaSet(std::string_view self, std::string_view owner) {
  std::optional<HostPort> a = ParseHostPort(self);
  std::optional<HostPort> b = ParseHostPort(owner);
  if (!a || !b) return false;
  if (a->host == b->host) return true;
  if (a->ip_literal || b->ip_literal) return false;
  const size_t da = a->host.find('.');
  const size_t db = b->host.find('.');
  // Both need a parent domain of two labels or more: "svc" alone (or a
  // top-level domain) would admit far too much.
  if (da == std::string::npos || db == std::string::npos) return false;
  const std::string_view pa = std::string_view(a->host).substr(da + 1);
  const std::string_view pb = std::string_view(b->host).substr(db + 1);
  return pa == pb && pa.find('.') != std::string_view::npos;
}

void Forwarder::SetAdvertise(std::string advertise) {
  std::lock_guard<std::mutex> lock(mu_);
  advertise_ = std::move(advertise);
}

std::string Forwarder::advertise() const {
  std::lock_guard<std::mutex> lock(mu_);
  return advertise_;
}

std::optional<std::string> Forwarder::Route(
    const grpc::CallbackServerContext& context, std::string_view job_id) const {
  if (context.client_metadata().count(kForwardedByKey) > 0) return std::nullopt;
  std::optional<std::string> owner = JobOwner(job_id);
  if (!owner) return std::nullopt;
  const std::string self = advertise();
  if (*owner == self || !SameReplicaSet(self, *owner)) return std::nullopt;
  return owner;
}

std::shared_ptr<v1::InterSlice::Stub> Forwarder::StubFor(
    const std::string& owner) {
  std::lock_guard<std::mutex> lock(mu_);
  if (stubs_.size() >= kMaxChannels && stubs_.count(owner) == 0) {
    stubs_.clear();
  }
  std::shared_ptr<v1::InterSlice::Stub>& stub = stubs_[owner];
  if (!stub) {
    grpc::ChannelArguments args;
    // A restarted owner is used again within a second or so, and a pod that
    // came back with a new IP address is found by its name again.
    // GRPC_ARG_MIN_RECONNECT_BACKOFF_MS is what gRPC gives one connection
    // attempt (TLS handshake included): 5 s, not 200 ms, which made a loaded
    // owner "unavailable" (as in client/grpc_channel.cc).
    args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 200);
    args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 5000);
    args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
    args.SetInt(GRPC_ARG_DNS_MIN_TIME_BETWEEN_RESOLUTIONS_MS, 1000);
    args.SetInt(GRPC_ARG_ENABLE_RETRIES, 0);
    stub = v1::InterSlice::NewStub(
        grpc::CreateCustomChannel(owner, credentials_, args));
  }
  return stub;
}

std::unique_ptr<grpc::ClientContext> Forwarder::ForwardContext(
    grpc::CallbackServerContext* context) const {
  // The caller's deadline and cancellation.
  std::unique_ptr<grpc::ClientContext> forwarded =
      grpc::ClientContext::FromCallbackServerContext(*context);
  const auto& metadata = context->client_metadata();
  auto token = metadata.find("authorization");
  if (token != metadata.end()) {
    forwarded->AddMetadata("authorization", std::string(token->second.data(),
                                                        token->second.size()));
  }
  forwarded->AddMetadata(kForwardedByKey, advertise());
  return forwarded;
}

grpc::ServerWriteReactor<v1::JobStatus>* Forwarder::Watch(
    grpc::CallbackServerContext* context, const v1::WatchRequest& request,
    const std::string& owner) {
  return new ForwardedStream<v1::WatchRequest, v1::JobStatus>(
      ForwardContext(context), request, owner, StubFor(owner).get(),
      &v1::InterSlice::StubInterface::async_interface::Watch);
}

grpc::ServerWriteReactor<v1::ArtifactChunk>* Forwarder::Fetch(
    grpc::CallbackServerContext* context, const v1::FetchRequest& request,
    const std::string& owner) {
  return new ForwardedStream<v1::FetchRequest, v1::ArtifactChunk>(
      ForwardContext(context), request, owner, StubFor(owner).get(),
      &v1::InterSlice::StubInterface::async_interface::Fetch);
}

void Forwarder::Cancel(grpc::CallbackServerContext* context,
                       grpc::ServerUnaryReactor* reactor,
                       const v1::CancelRequest& request,
                       v1::JobStatus* response, const std::string& owner) {
  struct Call {
    std::unique_ptr<grpc::ClientContext> context;
    v1::CancelRequest request;
  };
  auto* call = new Call{ForwardContext(context), request};
  StubFor(owner)->async()->Cancel(call->context.get(), &call->request, response,
                                  [reactor, call, owner](grpc::Status status) {
                                    delete call;
                                    reactor->Finish(OwnerStatus(status, owner));
                                  });
}

}  // namespace interslice::server
