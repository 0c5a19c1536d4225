// The DICOM node's RPCs: Find (a C-FIND on a DICOM peer) and the DICOM
// listener's kept series (ListKept, RerunKept). Each is for admin identities
// only (or any caller when the server authenticates nobody).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "server/net/grpc/service.h"
#include "server/net/grpc/status_map.h"
#include "server/node/peer.h"
#include "server/node/peer_registry.h"
#include "server/node/series_assembler.h"
#include "spdlog/spdlog.h"

namespace interslice::server {

grpc::ServerUnaryReactor* InterSliceService::Find(
    grpc::CallbackServerContext* context, const v1::FindRequest* request,
    v1::FindResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // Every query is audited (issue 39: none was): who asked which peer, with
  // which keys (their names, never their values: a patient ID is PHI), and
  // what came back (counts) or why nothing did.
  std::vector<std::string> keys;
  if (!request->patient_id().empty()) keys.push_back("patient_id");
  if (!request->study_date().empty()) keys.push_back("study_date");
  if (!request->modality().empty()) keys.push_back("modality");
  if (!request->accession_number().empty()) keys.push_back("accession_number");
  AuditEvent audited;
  audited.event = "find.queried";
  audited.identity = caller->identity;
  audited.source = context->peer();
  audited.peer = request->peer();
  audited.detail =
      absl::StrCat("keys: ", keys.empty() ? "none" : absl::StrJoin(keys, ", "));
  auto refuse = [&](grpc::Status status) {
    audited.outcome = AuditOutcome::kMinorFailure;
    absl::StrAppend(&audited.detail, "; refused: ", status.error_message());
    Audit(std::move(audited));
    reactor->Finish(status);
    return reactor;
  };
  // A PACS's index lists every patient's studies: not any one caller's.
  if (!caller->admin && !caller->identity.empty()) {
    return refuse(grpc::Status(
        grpc::PERMISSION_DENIED,
        "Find lists a DICOM peer's studies: admin identities only"));
  }
  std::shared_ptr<node::PeerClient> peer;
  if (peers_ != nullptr) peer = peers_->Find(request->peer());
  if (peer == nullptr) {
    return refuse(ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("peer: unknown DICOM peer \"", LogSafe(request->peer()),
                     "\" (see the server's --dicom-peers file)"))));
  }
  node::FindQuery query{request->patient_id(), request->study_date(),
                        request->modality(), request->accession_number()};
  if (absl::Status s = node::CheckFindQuery(query); !s.ok()) {
    return refuse(ToGrpcStatus(s));
  }
  const auto cap = [](int32_t asked, int fallback, int most) {
    if (asked <= 0) return fallback;
    return std::min<int>(asked, most);
  };
  node::FindLimits limits;
  limits.max_studies = cap(request->max_studies(), 100, 1000);
  limits.max_series = cap(request->max_series(), 1000, 10000);
  if (dicom_queries_in_flight_.fetch_add(1) >= kMaxDicomQueries) {
    dicom_queries_in_flight_.fetch_sub(1);
    return refuse(grpc::Status(
        grpc::RESOURCE_EXHAUSTED,
        absl::StrCat("already ", kMaxDicomQueries,
                     " DICOM queries in progress; try again shortly")));
  }
  dicom_queries_->Post([this, reactor, response, peer, query, limits,
                        audited = std::move(audited)]() mutable {
    const auto started = std::chrono::steady_clock::now();
    absl::StatusOr<node::FindResult> found = peer->Find(query, limits);
    dicom_queries_in_flight_.fetch_sub(1);
    const double seconds = std::chrono::duration<double>(
                               std::chrono::steady_clock::now() - started)
                               .count();
    if (!found.ok()) {
      spdlog::info("find on peer {} failed after {:.2f} s: {}",
                   LogSafe(peer->name()), seconds,
                   RedactPhi(found.status().message()));
      audited.outcome = AuditOutcome::kSeriousFailure;
      absl::StrAppend(&audited.detail,
                      "; failed: ", RedactPhi(found.status().message()));
      Audit(std::move(audited));
      reactor->Finish(ToGrpcStatus(found.status()));
      return;
    }
    int series = 0;
    for (node::FoundStudy& s : found->studies) {
      v1::FoundStudy* study = response->add_studies();
      study->set_study_instance_uid(std::move(s.study_instance_uid));
      study->set_patient_id(std::move(s.patient_id));
      study->set_study_date(std::move(s.study_date));
      study->set_accession_number(std::move(s.accession_number));
      study->set_study_description(std::move(s.study_description));
      study->set_modalities_in_study(std::move(s.modalities));
      for (node::FoundSeries& r : s.series) {
        v1::FoundSeries* out = study->add_series();
        out->set_series_instance_uid(std::move(r.series_instance_uid));
        out->set_modality(std::move(r.modality));
        out->set_series_number(std::move(r.series_number));
        out->set_series_description(std::move(r.series_description));
        out->set_instances(r.instances);
        ++series;
      }
    }
    response->set_truncated(found->truncated);
    response->set_max_studies(limits.max_studies);
    response->set_max_series(limits.max_series);
    // Counts only: no keys, no UIDs.
    spdlog::info("find on peer {}: {} study(ies), {} series{} in {:.2f} s",
                 LogSafe(peer->name()), response->studies_size(), series,
                 found->truncated ? " (truncated at the caps)" : "", seconds);
    audited.count = response->studies_size();
    absl::StrAppend(&audited.detail, "; ", response->studies_size(),
                    " study(ies), ", series, " series",
                    found->truncated ? " (truncated)" : "");
    Audit(std::move(audited));
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::ListKept(
    grpc::CallbackServerContext* context, const v1::ListKeptRequest* request,
    v1::ListKeptResponse* response) {
  (void)request;
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // Every sender's series, UIDs included: not any one caller's.
  if (!caller->admin && !caller->identity.empty()) {
    reactor->Finish(grpc::Status(
        grpc::PERMISSION_DENIED,
        "ListKept lists the DICOM listener's series: admin identities only"));
    return reactor;
  }
  if (assembler_ == nullptr) {
    reactor->Finish(grpc::Status(
        grpc::FAILED_PRECONDITION,
        "the server has no DICOM listener (--dicom-listen): nothing is kept"));
    return reactor;
  }
  io_->Post([this, reactor, response, identity = caller->identity,
             source = context->peer()] {
    for (node::KeptSeries& k : assembler_->ListKept()) {
      v1::ListKeptResponse::Series* s = response->add_series();
      s->set_id(std::move(k.id));
      s->set_calling_ae(std::move(k.calling_ae));
      s->set_called_ae(std::move(k.called_ae));
      s->set_modality(std::move(k.modality));
      s->set_instance_count(k.instances);
      s->set_kept_since_unix_ms(k.kept_since_unix_ms);
      s->set_why(std::move(k.why));
      s->set_job_id(std::move(k.job_id));
      s->set_study_instance_uid(std::move(k.study_uid));
      s->set_series_instance_uid(std::move(k.series_uid));
      s->set_state(std::move(k.state));
    }
    AuditEvent listed;
    listed.event = "kept.listed";
    listed.identity = identity;
    listed.source = source;
    listed.count = response->series_size();
    Audit(std::move(listed));
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::RerunKept(
    grpc::CallbackServerContext* context, const v1::RerunKeptRequest* request,
    v1::RerunKeptResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // It makes jobs of any sender's series.
  if (!caller->admin && !caller->identity.empty()) {
    reactor->Finish(grpc::Status(
        grpc::PERMISSION_DENIED,
        "RerunKept runs the DICOM listener's series: admin identities only"));
    return reactor;
  }
  if (request->all_unmatched() == !request->id().empty()) {
    reactor->Finish(
        grpc::Status(grpc::INVALID_ARGUMENT,
                     "give either the id of one kept series or all_unmatched"));
    return reactor;
  }
  if (assembler_ == nullptr) {
    reactor->Finish(grpc::Status(
        grpc::FAILED_PRECONDITION,
        "the server has no DICOM listener (--dicom-listen): nothing is kept"));
    return reactor;
  }
  io_->Post([this, reactor, response, id = request->id(),
             all = request->all_unmatched(), identity = caller->identity,
             source = context->peer()] {
    absl::StatusOr<std::vector<node::KeptRerun>> reruns;
    if (all) {
      reruns = assembler_->RerunAllUnmatched();
    } else if (absl::StatusOr<node::KeptRerun> one = assembler_->RerunKept(id);
               one.ok()) {
      reruns = std::vector<node::KeptRerun>{*std::move(one)};
    } else {
      reruns = one.status();
    }
    AuditEvent event;
    event.event = "kept.rerun";
    event.identity = identity;
    event.source = source;
    if (!reruns.ok()) {
      event.outcome = AuditOutcome::kMinorFailure;
      event.detail = std::string(reruns.status().message());
      Audit(std::move(event));
      reactor->Finish(ToGrpcStatus(reruns.status()));
      return;
    }
    for (const node::KeptRerun& r : *reruns) {
      if (!r.job_id.empty()) response->add_job_ids(r.job_id);
      if (!r.not_matched.empty()) {
        response->add_not_matched(absl::StrCat(r.id, ": ", r.not_matched));
      }
    }
    event.count = response->job_ids_size();
    event.detail =
        absl::StrCat(all ? "all unmatched" : "one series", ": ",
                     response->job_ids_size(), " job(s) made, ",
                     response->not_matched_size(), " without a matching rule");
    Audit(std::move(event));
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

}  // namespace interslice::server
