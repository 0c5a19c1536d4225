#include "server/net/dimse/connection_gate.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dimse {

int64_t SteadyMillisNow() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

void RefusalLog::Refused(const char* reason, const std::string& source,
                         const std::string& detail) {
  if (metrics_ != nullptr) metrics_->DicomConnectionRefused(reason);
  const auto now = std::chrono::steady_clock::now();
  bool log = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    PerReason& r = reasons_[reason];
    if (now - r.window >= std::chrono::seconds(1) && r.suppressed == 0) {
      r.window = now;
      r.logged = 0;
    }
    if (r.logged < 10) {
      ++r.logged;
      log = true;
    } else {
      ++r.suppressed;
    }
  }
  if (log) {
    spdlog::warn("dicom: connection from {} refused or cut ({}): {}",
                 LogSafe(source), reason, LogSafe(detail));
    if (audit_ != nullptr) {
      AuditEvent e;
      e.event = "association.refused";
      e.outcome = AuditOutcome::kMinorFailure;
      e.source = source;
      e.detail = absl::StrCat(reason, ": ", detail);
      audit_->Record(std::move(e));
    }
  }
}

void RefusalLog::Flush() {
  const auto now = std::chrono::steady_clock::now();
  std::vector<std::pair<std::string, int64_t>> sums;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto& [reason, r] : reasons_) {
      if (r.suppressed == 0 || now - r.window < std::chrono::seconds(10)) {
        continue;
      }
      sums.emplace_back(reason, r.suppressed);
      r.suppressed = 0;
      r.window = now;
      r.logged = 0;
    }
  }
  for (const auto& [reason, n] : sums) {
    spdlog::warn(
        "dicom: {} more connection(s) refused or cut ({}) in the last 10 s, "
        "not logged one by one",
        n, reason);
    if (audit_ != nullptr) {
      AuditEvent e;
      e.event = "association.refused";
      e.outcome = AuditOutcome::kMinorFailure;
      e.count = n;
      e.detail = absl::StrCat(reason, ": ", n,
                              " more refused in the last 10 s, not recorded "
                              "one by one");
      audit_->Record(std::move(e));
    }
  }
}

namespace {

std::string Numeric(const sockaddr_storage& a) {
  char text[INET6_ADDRSTRLEN] = "";
  if (a.ss_family == AF_INET) {
    inet_ntop(AF_INET, &reinterpret_cast<const sockaddr_in&>(a).sin_addr, text,
              sizeof(text));
  } else if (a.ss_family == AF_INET6) {
    const auto& six = reinterpret_cast<const sockaddr_in6&>(a);
    if (IN6_IS_ADDR_V4MAPPED(&six.sin6_addr)) {
      // A dual-stack socket's IPv4 peer: its IPv4 address.
      inet_ntop(AF_INET, &six.sin6_addr.s6_addr[12], text, sizeof(text));
    } else {
      inet_ntop(AF_INET6, &six.sin6_addr, text, sizeof(text));
    }
  }
  return text;
}

void SetBlocking(int fd, bool blocking) {
  const int flags = ::fcntl(fd, F_GETFL);
  if (flags < 0) return;
  ::fcntl(fd, F_SETFL, blocking ? (flags & ~O_NONBLOCK) : (flags | O_NONBLOCK));
}

// PS3.8 9.3.4: A-ASSOCIATE-RJ, rejected-transient (2), service provider
// (presentation related function, 3), local limit exceeded (2).
void SendBusyRejection(int fd) {
  const unsigned char rj[10] = {0x03, 0, 0, 0, 0, 4, 0, 2, 3, 2};
  (void)!::send(fd, rj, sizeof(rj), MSG_NOSIGNAL | MSG_DONTWAIT);
}

}  // namespace

struct ConnectionGate::Pending {
  int fd = -1;
  std::string source;
  sockaddr_storage address{};
  int64_t accepted_ms = 0;
  int64_t deadline_ms = 0;
  std::string buffer;
  std::unique_ptr<PduGuard> guard;
  bool ready = false;
};

absl::StatusOr<std::unique_ptr<ConnectionGate>> ConnectionGate::Bind(
    const GateOptions& options, RefusalLog* refusals) {
  std::unique_ptr<ConnectionGate> gate(new ConnectionGate(options, refusals));
  std::string host = options.host;
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  if (host.empty() || host == "*") host = "0.0.0.0";
  if (host == "localhost") host = "127.0.0.1";
  sockaddr_storage addr{};
  socklen_t addr_len = 0;
  auto* v4 = reinterpret_cast<sockaddr_in*>(&addr);
  auto* v6 = reinterpret_cast<sockaddr_in6*>(&addr);
  if (inet_pton(AF_INET, host.c_str(), &v4->sin_addr) == 1) {
    v4->sin_family = AF_INET;
    v4->sin_port = htons(static_cast<uint16_t>(options.port));
    addr_len = sizeof(sockaddr_in);
  } else if (inet_pton(AF_INET6, host.c_str(), &v6->sin6_addr) == 1) {
    v6->sin6_family = AF_INET6;
    v6->sin6_port = htons(static_cast<uint16_t>(options.port));
    addr_len = sizeof(sockaddr_in6);
  } else {
    return absl::InvalidArgumentError(absl::StrCat(
        "--dicom-listen: '", LogSafe(options.host),
        "' is not a numeric IPv4 or IPv6 address (or * for every interface)"));
  }
  const std::string where = absl::StrCat(
      addr.ss_family == AF_INET6 ? absl::StrCat("[", host, "]") : host, ":",
      options.port);
  const int fd =
      ::socket(addr.ss_family, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen for DICOM on ", where, ": ", std::strerror(errno)));
  }
  gate->listen_fd_ = fd;
  const int on = 1, off = 0;
  // A predecessor's connections in TIME_WAIT must not stop a restart.
  ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &on, sizeof(on));
  if (addr.ss_family == AF_INET6) {
    // "::" serves IPv4 peers too (as mapped addresses).
    ::setsockopt(fd, IPPROTO_IPV6, IPV6_V6ONLY, &off, sizeof(off));
  }
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), addr_len) != 0 ||
      ::listen(fd, 128) != 0) {
    const int e = errno;
    std::string why = std::strerror(e);
    if (e == EADDRINUSE) why = "the address is in use";
    if (e == EADDRNOTAVAIL) why = "it is not an address of this host";
    if (e == EACCES) why = "permission denied (ports below 1024 need it)";
    return absl::UnavailableError(
        absl::StrCat("cannot listen for DICOM on ", where, ": ", why));
  }
  sockaddr_storage bound{};
  socklen_t bound_len = sizeof(bound);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&bound), &bound_len);
  gate->port_ = ntohs(bound.ss_family == AF_INET6
                          ? reinterpret_cast<sockaddr_in6&>(bound).sin6_port
                          : reinterpret_cast<sockaddr_in&>(bound).sin_port);
  gate->address_ = host;
  if (::pipe2(gate->wake_, O_CLOEXEC | O_NONBLOCK) != 0) {
    return absl::InternalError("cannot create the listener's wake-up pipe");
  }
  return gate;
}

ConnectionGate::~ConnectionGate() {
  Stop();
  if (listen_fd_ >= 0) ::close(listen_fd_);
  for (int fd : wake_) {
    if (fd >= 0) ::close(fd);
  }
}

void ConnectionGate::Start(std::function<Handoff(ReadyConnection&)> handoff) {
  handoff_ = std::move(handoff);
  thread_ = std::thread([this] { Loop(); });
}

void ConnectionGate::StopAccepting() {
  accepting_ = false;
  (void)!::write(wake_[1], "a", 1);
}

void ConnectionGate::Stop() {
  stopping_ = true;
  accepting_ = false;
  if (wake_[1] >= 0) (void)!::write(wake_[1], "s", 1);
  if (thread_.joinable()) thread_.join();
}

void ConnectionGate::Unwatch(const std::shared_ptr<ConnectionWatch>& watch) {
  if (watch == nullptr) return;
  std::lock_guard<std::mutex> lock(watch_mu_);
  watched_.erase(watch.get());
}

void ConnectionGate::Evict(std::map<int64_t, Pending>::iterator it,
                           const char* reason, const std::string& detail) {
  refusals_->Refused(reason, it->second.source, detail);
  ::close(it->second.fd);
  pending_->erase(it);
}

void ConnectionGate::AcceptAll() {
  while (accepting_) {
    Pending p;
    socklen_t len = sizeof(p.address);
    p.fd = ::accept4(listen_fd_, reinterpret_cast<sockaddr*>(&p.address), &len,
                     SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (p.fd < 0) {
      if (errno == EINTR || errno == ECONNABORTED) continue;
      if (errno != EAGAIN && errno != EWOULDBLOCK) {
        // Out of file descriptors, say: the connections wait in the
        // backlog; try again at the next tick.
        spdlog::warn("dicom: cannot accept a connection: {}",
                     std::strerror(errno));
      }
      return;
    }
    p.source = Numeric(p.address);
    p.accepted_ms = SteadyMillisNow();
    p.deadline_ms =
        p.accepted_ms +
        static_cast<int64_t>(options_.request_timeout_seconds * 1000);
    p.guard = std::make_unique<PduGuard>(options_.guard);
    // DIMSE is request/response: Nagle's algorithm with delayed ACKs costs
    // about 40 ms an exchange (DESIGN.md section 7).
    const int on = 1;
    ::setsockopt(p.fd, IPPROTO_TCP, TCP_NODELAY, &on, sizeof(on));
    timeval send_timeout{};
    send_timeout.tv_sec = static_cast<time_t>(options_.send_timeout_seconds);
    ::setsockopt(p.fd, SOL_SOCKET, SO_SNDTIMEO, &send_timeout,
                 sizeof(send_timeout));
    // Room for it: the oldest waiting connection of its address, else the
    // oldest of all, gives way.
    int from_source = 0;
    auto oldest_of_source = pending_->end();
    for (auto it = pending_->begin(); it != pending_->end(); ++it) {
      if (it->second.source == p.source) {
        if (from_source++ == 0) oldest_of_source = it;
      }
    }
    if (from_source >= options_.max_pending_per_source) {
      Evict(oldest_of_source, refusal::kPendingPerSource,
            absl::StrCat("the oldest of ", from_source,
                         " connections from this address waiting for their "
                         "association request made room for a new one"));
    } else if (static_cast<int>(pending_->size()) >= options_.max_pending) {
      Evict(pending_->begin(), refusal::kPendingTotal,
            absl::StrCat("the oldest of ", pending_->size(),
                         " connections waiting for their association "
                         "request made room for a new one"));
    }
    (*pending_)[next_pending_++] = std::move(p);
  }
}

bool ConnectionGate::ReadRequest(Pending& p, int64_t now) {
  if (options_.tls) {
    // The first bytes of a TLS handshake are there: DCMTK's from here on.
    char first;
    const ssize_t r = ::recv(p.fd, &first, 1, MSG_PEEK | MSG_DONTWAIT);
    if (r < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
      return false;
    }
    if (r <= 0) {
      ::close(p.fd);
      p.fd = -1;
      return true;
    }
    p.ready = true;
    return true;
  }
  while (true) {
    // Read no further than the request: the header, then its body.
    size_t want = 6;
    if (p.buffer.size() >= 6) {
      want = static_cast<size_t>(p.guard->request_bytes_left());
      if (want == 0) want = 1;
    } else {
      want = 6 - p.buffer.size();
    }
    char chunk[16384];
    const ssize_t r =
        ::recv(p.fd, chunk, std::min(want, sizeof(chunk)), MSG_DONTWAIT);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) return false;
    if (r <= 0) {
      // Closed before the request: nothing to refuse (a port scan, a
      // health check), unless it had begun one.
      if (!p.buffer.empty()) {
        refusals_->Refused(
            refusal::kBadRequest, p.source,
            absl::StrCat("the connection closed after ", p.buffer.size(),
                         " bytes of an association request"));
      }
      ::close(p.fd);
      p.fd = -1;
      return true;
    }
    const auto* bytes = reinterpret_cast<const unsigned char*>(chunk);
    if (absl::Status s = p.guard->Feed(bytes, static_cast<size_t>(r));
        !s.ok()) {
      refusals_->Refused(refusal::kBadRequest, p.source,
                         std::string(s.message()));
      ::close(p.fd);
      p.fd = -1;
      return true;
    }
    p.buffer.append(chunk, static_cast<size_t>(r));
    if (p.guard->request_complete()) {
      p.ready = true;
      return true;
    }
    (void)now;
  }
}

void ConnectionGate::HandOver(std::map<int64_t, Pending>::iterator it) {
  Pending& p = it->second;
  ReadyConnection c;
  c.fd = p.fd;
  c.source = p.source;
  c.address = p.address;
  c.preread = std::move(p.buffer);
  c.guard = std::move(p.guard);
  c.request_deadline_ms = p.deadline_ms;
  c.watch = std::make_shared<ConnectionWatch>(p.fd, p.source);
  c.watch->SetDeadline(p.deadline_ms, refusal::kRequestDeadline);
  SetBlocking(p.fd, true);
  {
    std::lock_guard<std::mutex> lock(watch_mu_);
    watched_[c.watch.get()] = c.watch;
  }
  const Handoff result = handoff_(c);
  if (result != Handoff::kTaken) {
    Unwatch(c.watch);
    const bool plain = !options_.tls;
    if (plain) SendBusyRejection(p.fd);
    refusals_->Refused(
        result == Handoff::kBusy ? refusal::kBusy : refusal::kPerSource,
        p.source,
        absl::StrCat(
            result == Handoff::kBusy
                ? "every association slot is taken"
                : "this address has as many associations as allowed",
            plain ? " (A-ASSOCIATE-RJ: local limit exceeded)" : " (closed)"));
    ::close(p.fd);
  }
  pending_->erase(it);
}

void ConnectionGate::CheckWatches(int64_t now) {
  std::lock_guard<std::mutex> lock(watch_mu_);
  for (auto& [raw, watch] : watched_) {
    const int64_t deadline = watch->deadline_ms_.load();
    if (deadline == 0 || now < deadline || watch->cut_.load()) continue;
    watch->cut_ = true;
    // Ends any read or write blocked on it (TLS included); its owner sees
    // the connection close and ends the association.
    ::shutdown(watch->fd_, SHUT_RDWR);
    const char* reason = watch->reason_.load();
    refusals_->Refused(
        reason != nullptr ? reason : refusal::kPduDeadline, watch->source_,
        reason == refusal::kRequestDeadline
            ? "the association request did not arrive in time"
            : "a PDU did not arrive complete in time (a sender too slow)");
  }
}

void ConnectionGate::Loop() {
  std::map<int64_t, Pending> pending;
  pending_ = &pending;
  bool listening = true;
  while (!stopping_) {
    if (listening && !accepting_) {
      listening = false;
      ::close(listen_fd_);
      listen_fd_ = -1;
      for (auto& [seq, p] : pending) ::close(p.fd);
      pending.clear();
    }
    std::vector<pollfd> fds;
    fds.push_back({wake_[0], POLLIN, 0});
    if (listening) fds.push_back({listen_fd_, POLLIN, 0});
    std::vector<int64_t> order;
    int64_t now = SteadyMillisNow();
    int64_t next = now + 250;  // the watchdog's tick
    for (auto& [seq, p] : pending) {
      fds.push_back({p.fd, POLLIN, 0});
      order.push_back(seq);
      next = std::min(next, p.deadline_ms);
    }
    const int timeout = static_cast<int>(std::max<int64_t>(0, next - now));
    const int n = ::poll(fds.data(), fds.size(), timeout);
    if (n < 0 && errno != EINTR) {
      spdlog::error("dicom: the listener's poll failed: {}",
                    std::strerror(errno));
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    if (fds[0].revents & POLLIN) {
      char drain[64];
      while (::read(wake_[0], drain, sizeof(drain)) > 0) {
      }
    }
    now = SteadyMillisNow();
    const size_t first = listening ? 2 : 1;
    for (size_t i = 0; i < order.size(); ++i) {
      auto it = pending.find(order[i]);
      if (it == pending.end()) continue;  // evicted meanwhile
      Pending& p = it->second;
      if (fds[first + i].revents != 0 && ReadRequest(p, now)) {
        if (p.fd < 0) {
          pending.erase(it);
        } else {
          HandOver(it);
        }
        continue;
      }
      if (now >= p.deadline_ms) {
        Evict(it, refusal::kRequestDeadline,
              p.buffer.empty()
                  ? absl::StrCat("no association request within ",
                                 options_.request_timeout_seconds, " s")
                  : absl::StrCat("the association request was not complete "
                                 "within ",
                                 options_.request_timeout_seconds, " s (",
                                 p.buffer.size(), " bytes came)"));
      }
    }
    if (listening && (fds[1].revents & POLLIN)) AcceptAll();
    CheckWatches(now);
    refusals_->Flush();
  }
  for (auto& [seq, p] : pending) ::close(p.fd);
  pending.clear();
  pending_ = nullptr;
}

}  // namespace interslice::server::dimse
