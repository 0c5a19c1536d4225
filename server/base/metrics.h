// Prometheus metrics (prometheus-cpp), served on --metrics-listen.
#ifndef INTERSLICE_SERVER_BASE_METRICS_H_
#define INTERSLICE_SERVER_BASE_METRICS_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace prometheus {
class Registry;
class Exposer;
class Counter;
class Gauge;
template <typename T>
class Family;
class Histogram;
}  // namespace prometheus

namespace interslice::server {

class Metrics {
 public:
  Metrics();
  ~Metrics();
  // Starts the HTTP endpoint (/metrics) on host:port; port 0 picks one.
  absl::Status Serve(const std::string& listen);
  int port() const { return port_; }

  // outcome: "succeeded", "failed", "cancelled", "rejected".
  void JobFinished(const std::string& outcome);
  void SetQueueDepth(double n);
  void SetRunning(double n);
  void StageSeconds(const std::string& stage, double seconds);
  void BytesIn(double n);
  void BytesOut(double n);
  // DICOM instances stored on (or refused by) a peer, by peer name.
  void DicomInstancesSent(const std::string& peer, double n);
  void DicomInstancesFailed(const std::string& peer, double n);
  // The DICOM listener (interslice_dicom_events_total{event=...}):
  // "associations", "associations_rejected", "instances_received",
  // "instances_refused", "series_completed", "jobs_created",
  // "series_incomplete" (a series became incomplete: a broken transfer),
  // "series_incomplete_dropped" (an incomplete series waited in vain),
  // "presentation_contexts_refused" (contexts of accepted associations
  // refused in negotiation, e.g. a getscu's C-GET).
  void DicomEvent(const std::string& event, double n = 1);
  // A connection to the DICOM listener refused or cut, by reason
  // (interslice_dicom_connections_refused_total{reason=...}; the reasons
  // are listed in server/net/dimse/connection_gate.h).
  void DicomConnectionRefused(const std::string& reason);
  // interslice_dicom_peer_reachable{peer}: 1 when the peer's last C-ECHO
  // (at start-up) was answered, 0 when not.
  void DicomPeerReachable(const std::string& peer, bool reachable);
  // interslice_dicom_config_generation: 1 at start, +1 per SIGHUP reload
  // of the peers and rules files that was taken (a refused one leaves it).
  void DicomConfigGeneration(int generation);
  // The HTTP listener: interslice_http_requests_total{route, code}, route
  // "status" (the status page, /metrics is not on it) or a route handler's
  // name ("STOW-RS"), code the HTTP status answered.
  void HttpRequest(const std::string& route, int code);
  // STOW-RS: interslice_stow_instances_total{outcome} ("stored",
  // "refused") and interslice_stow_body_bytes_total (request body bytes
  // read, whole or not).
  void StowInstances(const std::string& outcome, double n);
  void StowBodyBytes(double n);

 private:
  std::shared_ptr<prometheus::Registry> registry_;
  std::unique_ptr<prometheus::Exposer> exposer_;
  prometheus::Family<prometheus::Counter>* jobs_;
  prometheus::Family<prometheus::Histogram>* stages_;
  prometheus::Family<prometheus::Counter>* dicom_;
  prometheus::Gauge* queue_depth_;
  prometheus::Gauge* running_;
  prometheus::Counter* bytes_in_;
  prometheus::Counter* bytes_out_;
  prometheus::Family<prometheus::Counter>* dicom_sent_;
  prometheus::Family<prometheus::Counter>* dicom_send_failed_;
  prometheus::Family<prometheus::Counter>* dicom_refused_;
  prometheus::Family<prometheus::Gauge>* dicom_peer_reachable_;
  prometheus::Gauge* dicom_config_generation_;
  prometheus::Family<prometheus::Counter>* http_requests_;
  prometheus::Family<prometheus::Counter>* stow_instances_;
  prometheus::Counter* stow_body_bytes_;
  int port_ = 0;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_METRICS_H_
