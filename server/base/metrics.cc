#include "server/base/metrics.h"

#include <exception>

#include "absl/strings/str_cat.h"
#include "prometheus/counter.h"
#include "prometheus/exposer.h"
#include "prometheus/gauge.h"
#include "prometheus/histogram.h"
#include "prometheus/registry.h"

namespace interslice::server {

Metrics::Metrics() : registry_(std::make_shared<prometheus::Registry>()) {
  jobs_ = &prometheus::BuildCounter()
               .Name("interslice_jobs_total")
               .Help("Jobs that ended, by outcome")
               .Register(*registry_);
  stages_ = &prometheus::BuildHistogram()
                 .Name("interslice_stage_duration_seconds")
                 .Help("Duration of pipeline stages")
                 .Register(*registry_);
  queue_depth_ = &prometheus::BuildGauge()
                      .Name("interslice_queue_depth")
                      .Help("Jobs uploading or waiting for a worker")
                      .Register(*registry_)
                      .Add({});
  running_ = &prometheus::BuildGauge()
                  .Name("interslice_running_jobs")
                  .Help("Jobs running now")
                  .Register(*registry_)
                  .Add({});
  bytes_in_ = &prometheus::BuildCounter()
                   .Name("interslice_bytes_received_total")
                   .Help("DICOM bytes uploaded")
                   .Register(*registry_)
                   .Add({});
  dicom_sent_ = &prometheus::BuildCounter()
                     .Name("interslice_dicom_instances_sent_total")
                     .Help(
                         "DICOM instances a peer accepted (C-STORE), by "
                         "peer name")
                     .Register(*registry_);
  dicom_send_failed_ =
      &prometheus::BuildCounter()
           .Name("interslice_dicom_instances_send_failed_total")
           .Help(
               "DICOM instances not stored on a peer in a try (refused, "
               "or the peer unreachable), by peer name")
           .Register(*registry_);
  bytes_out_ = &prometheus::BuildCounter()
                    .Name("interslice_bytes_sent_total")
                    .Help("Artifact bytes sent")
                    .Register(*registry_)
                    .Add({});
  for (const char* outcome : {"succeeded", "failed", "cancelled", "rejected"}) {
    jobs_->Add({{"outcome", outcome}});
  }
  dicom_ = &prometheus::BuildCounter()
                .Name("interslice_dicom_events_total")
                .Help(
                    "DICOM listener events: associations (accepted, "
                    "rejected), instances (received, refused, moved: "
                    "received for a C-MOVE of ours), series "
                    "completed, jobs created")
                .Register(*registry_);
  for (const char* event :
       {"associations", "associations_rejected", "instances_received",
        "instances_refused", "series_completed", "jobs_created",
        "series_incomplete", "series_incomplete_dropped",
        "presentation_contexts_refused", "config_reload_refused",
        "instances_moved", "series_resent_unchanged",
        "instances_other_frame_of_reference", "series_resend_not_completing",
        "own_results_not_run"}) {
    dicom_->Add({{"event", event}});
  }
  http_requests_ = &prometheus::BuildCounter()
                        .Name("interslice_http_requests_total")
                        .Help(
                            "Requests the HTTP listener answered, by route "
                            "(status, STOW-RS) and HTTP status code")
                        .Register(*registry_);
  stow_instances_ = &prometheus::BuildCounter()
                         .Name("interslice_stow_instances_total")
                         .Help(
                             "Instances STOW-RS requests carried, by outcome "
                             "(stored, refused)")
                         .Register(*registry_);
  for (const char* outcome : {"stored", "refused"}) {
    stow_instances_->Add({{"outcome", outcome}});
  }
  stow_body_bytes_ = &prometheus::BuildCounter()
                          .Name("interslice_stow_body_bytes_total")
                          .Help("STOW-RS request body bytes read")
                          .Register(*registry_)
                          .Add({});
  dicom_refused_ =
      &prometheus::BuildCounter()
           .Name("interslice_dicom_connections_refused_total")
           .Help(
               "Connections to the DICOM listener refused or cut, by reason "
               "(before or during an association)")
           .Register(*registry_);
  dicom_peer_reachable_ =
      &prometheus::BuildGauge()
           .Name("interslice_dicom_peer_reachable")
           .Help(
               "1 when the peer answered the last C-ECHO (at start-up), 0 "
               "when not, by peer name")
           .Register(*registry_);
  dicom_config_generation_ =
      &prometheus::BuildGauge()
           .Name("interslice_dicom_config_generation")
           .Help(
               "The DICOM node's peers and rules in force: 1 at start, +1 "
               "per reload (SIGHUP) taken")
           .Register(*registry_)
           .Add({});
}

void Metrics::DicomConfigGeneration(int generation) {
  dicom_config_generation_->Set(generation);
}

void Metrics::DicomPeerReachable(const std::string& peer, bool reachable) {
  dicom_peer_reachable_->Add({{"peer", peer}}).Set(reachable ? 1 : 0);
}

void Metrics::DicomConnectionRefused(const std::string& reason) {
  dicom_refused_->Add({{"reason", reason}}).Increment();
}

void Metrics::HttpRequest(const std::string& route, int code) {
  http_requests_->Add({{"route", route}, {"code", std::to_string(code)}})
      .Increment();
}

void Metrics::StowInstances(const std::string& outcome, double n) {
  stow_instances_->Add({{"outcome", outcome}}).Increment(n);
}

void Metrics::StowBodyBytes(double n) { stow_body_bytes_->Increment(n); }

void Metrics::DicomEvent(const std::string& event, double n) {
  dicom_->Add({{"event", event}}).Increment(n);
}

Metrics::~Metrics() = default;

absl::Status Metrics::Serve(const std::string& listen) {
  try {
    exposer_ = std::make_unique<prometheus::Exposer>(listen);
  } catch (const std::exception& e) {
    return absl::UnavailableError(
        absl::StrCat("cannot serve metrics on ", listen, ": ", e.what()));
  }
  exposer_->RegisterCollectable(registry_);
  const auto ports = exposer_->GetListeningPorts();
  port_ = ports.empty() ? 0 : ports.front();
  return absl::OkStatus();
}

void Metrics::JobFinished(const std::string& outcome) {
  jobs_->Add({{"outcome", outcome}}).Increment();
}
void Metrics::SetQueueDepth(double n) { queue_depth_->Set(n); }
void Metrics::SetRunning(double n) { running_->Set(n); }
void Metrics::StageSeconds(const std::string& stage, double seconds) {
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600};
  stages_->Add({{"stage", stage}}, kBuckets).Observe(seconds);
}
void Metrics::BytesIn(double n) { bytes_in_->Increment(n); }
void Metrics::BytesOut(double n) { bytes_out_->Increment(n); }

void Metrics::DicomInstancesSent(const std::string& peer, double n) {
  dicom_sent_->Add({{"peer", peer}}).Increment(n);
}

void Metrics::DicomInstancesFailed(const std::string& peer, double n) {
  dicom_send_failed_->Add({{"peer", peer}}).Increment(n);
}

}  // namespace interslice::server
