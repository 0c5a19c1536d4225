// The DICOM listener's front door: the listening socket, the connections
// that have not yet sent their association request, and the deadlines of
// every connection (issue 22: the listener could be blocked before any
// authentication, and a taken port crashed the server).
//
// - Binds exactly the address given (IPv4 or IPv6, numeric; "*" or "" for
//   every IPv4 interface, "::" for every interface), with SO_REUSEADDR so
//   that a predecessor's TIME_WAIT connections do not stop a restart. A
//   taken port, an address that is not this host's, a port that needs
//   privileges: UNAVAILABLE with one line ("cannot listen for DICOM on
//   127.0.0.1:11112: the address is in use").
// - One thread accepts and waits for requests with poll(): a connection
//   costs a socket and a buffer, never a thread, until its A-ASSOCIATE-RQ
//   has arrived complete (plain TCP: the gate reads and checks it with a
//   PduGuard) or its first byte has (TLS: the handshake is DCMTK's, in the
//   association worker, under the same deadline). Only then is it handed
//   to the association workers.
// - Deadlines: the whole request must arrive within request_timeout of the
//   connection (a peer that sends nothing, or a byte a second, is cut
//   then). Connections handed over get a ConnectionWatch whose deadline
//   their reader moves (the rest of the request, then each PDU within
//   pdu_timeout of its first byte); the gate shuts down the socket of a
//   watched connection past its deadline, which ends any blocked read,
//   TLS included.
// - Limits: at most max_pending connections wait for their request, at most
//   max_pending_per_source from one address; a new connection beyond either
//   evicts the oldest waiting one (of that address, or overall), so that a
//   flood of idle connections cannot lock out a peer that speaks at once.
//   When the workers refuse a complete request (all busy, or too many
//   associations from its address), the gate answers A-ASSOCIATE-RJ
//   (transient, local limit exceeded) itself.
// - Every refused or cut connection is counted by reason
//   (interslice_dicom_connections_refused_total{reason}) and logged with
//   its address and the reason (at most 10 lines a second per reason; the
//   rest are summed in a line every 10 s). Addresses are not patient data.
#ifndef INTERSLICE_SERVER_NET_DIMSE_CONNECTION_GATE_H_
#define INTERSLICE_SERVER_NET_DIMSE_CONNECTION_GATE_H_

#include <sys/socket.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/statusor.h"
#include "server/net/dimse/pdu_guard.h"

namespace interslice::server {
class AuditLog;
class Metrics;
}  // namespace interslice::server

namespace interslice::server::dimse {

// Reasons (metric label values) for refused or cut connections.
namespace refusal {
inline constexpr char kPendingPerSource[] = "pending_per_source";
inline constexpr char kPendingTotal[] = "pending_total";
inline constexpr char kRequestDeadline[] = "request_deadline";
inline constexpr char kBadRequest[] = "bad_request";
inline constexpr char kBusy[] = "busy";
inline constexpr char kPerSource[] = "associations_per_source";
inline constexpr char kPduDeadline[] = "pdu_deadline";
inline constexpr char kProtocol[] = "protocol_violation";
inline constexpr char kTls[] = "tls_handshake";
inline constexpr char kCalledAe[] = "called_ae";
inline constexpr char kCallingAe[] = "calling_ae";
inline constexpr char kCallingAddress[] = "calling_address";
inline constexpr char kNoContext[] = "no_presentation_context";
inline constexpr char kOtherRejection[] = "rejected";
}  // namespace refusal

// Counts and logs refused or cut connections (thread-safe).
class RefusalLog {
 public:
  // `audit` (may be null): every refusal logged one by one is also an
  // audit record, and so is each sum of those that were not.
  explicit RefusalLog(Metrics* metrics, AuditLog* audit = nullptr)
      : metrics_(metrics), audit_(audit) {}
  // `source`: the peer's address; `detail`: what happened, no patient data.
  void Refused(const char* reason, const std::string& source,
               const std::string& detail);
  // Logs the sums of what was not logged one by one (the gate calls it).
  void Flush();

 private:
  struct PerReason {
    std::chrono::steady_clock::time_point window;
    int logged = 0;
    int64_t suppressed = 0;
  };
  Metrics* const metrics_;
  AuditLog* const audit_;
  std::mutex mu_;
  std::map<std::string, PerReason> reasons_;
};

// A handed-over connection's deadline, watched by the gate.
class ConnectionWatch {
 public:
  ConnectionWatch(int fd, std::string source)
      : fd_(fd), source_(std::move(source)) {}
  // Milliseconds on the steady clock (0: none), and what passing it means.
  void SetDeadline(int64_t steady_ms, const char* reason) {
    reason_.store(reason);
    deadline_ms_.store(steady_ms);
  }
  bool cut() const { return cut_.load(); }
  int fd() const { return fd_; }

 private:
  friend class ConnectionGate;
  const int fd_;
  const std::string source_;
  std::atomic<int64_t> deadline_ms_{0};
  std::atomic<const char*> reason_{nullptr};
  std::atomic<bool> cut_{false};
};

int64_t SteadyMillisNow();

struct GateOptions {
  std::string host;  // see above
  int port = 0;      // 0: a free port (see port())
  double request_timeout_seconds = 10;
  int max_pending = 64;
  int max_pending_per_source = 16;
  bool tls = false;
  // Socket send timeout: a peer that stops reading our responses cannot
  // hold a worker in a blocked write for longer.
  double send_timeout_seconds = 60;
  PduGuardLimits guard;
};

// A connection whose request has arrived (or, with TLS, begun).
struct ReadyConnection {
  int fd = -1;
  std::string source;  // numeric address
  sockaddr_storage address{};
  std::string preread;  // bytes read by the gate, already fed to `guard`
  std::unique_ptr<PduGuard> guard;
  std::shared_ptr<ConnectionWatch> watch;  // registered with the gate
  int64_t request_deadline_ms = 0;
  // Frees the connection's place in the listener's per-source count; called
  // as soon as the association's end begins (release request, abort), so
  // that a sender at its limit may associate again at once, and again when
  // the worker is done (only the first call counts). Empty: nothing to free.
  std::function<void()> release_slot;
};

enum class Handoff { kTaken, kBusy, kSourceBusy };

class ConnectionGate {
 public:
  static absl::StatusOr<std::unique_ptr<ConnectionGate>> Bind(
      const GateOptions& options, RefusalLog* refusals);
  ~ConnectionGate();  // Stop()

  int port() const { return port_; }
  const std::string& address() const { return address_; }

  // Starts the gate's thread. `handoff` runs on it and must not block; on
  // kTaken it owns the connection (fd, watch), else the gate refuses it.
  void Start(std::function<Handoff(ReadyConnection&)> handoff);
  // Closes the listening socket and every waiting connection; watched
  // connections keep their deadlines until Stop().
  void StopAccepting();
  void Stop();

  // Watched connections: registered when handed over, unregistered by their
  // owner before it closes the socket.
  void Unwatch(const std::shared_ptr<ConnectionWatch>& watch);

 private:
  struct Pending;
  ConnectionGate(const GateOptions& options, RefusalLog* refusals)
      : options_(options), refusals_(refusals) {}
  void Loop();
  void AcceptAll();
  void Evict(std::map<int64_t, Pending>::iterator it, const char* reason,
             const std::string& detail);
  // Reads what is there; true when the connection is ready or done with.
  bool ReadRequest(Pending& p, int64_t now);
  void HandOver(std::map<int64_t, Pending>::iterator it);
  void CheckWatches(int64_t now);

  const GateOptions options_;
  RefusalLog* const refusals_;
  int listen_fd_ = -1;
  int wake_[2] = {-1, -1};
  int port_ = 0;
  std::string address_;
  std::function<Handoff(ReadyConnection&)> handoff_;
  std::thread thread_;
  std::atomic<bool> accepting_{true};
  std::atomic<bool> stopping_{false};
  // Waiting connections by arrival order (a sequence number).
  std::map<int64_t, Pending>* pending_ = nullptr;
  int64_t next_pending_ = 0;
  std::mutex watch_mu_;
  std::map<ConnectionWatch*, std::shared_ptr<ConnectionWatch>> watched_;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_CONNECTION_GATE_H_
