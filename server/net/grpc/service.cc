// InterSliceService (service.h): authentication, the audit trail, where a
// job's calls are forwarded, GetServerInfo, and what the RPC files share
// (service_internal.h). The RPCs by group: service_upload.cc (Interpolate,
// Submit), service_jobs.cc (Watch, Fetch, Cancel, List) and
// service_dicom_node.cc (Find, ListKept, RerunKept).
#include "server/net/grpc/service.h"

#include <algorithm>
#include <cstdint>
#include <optional>
#include <string>
#include <utility>

#include "absl/status/statusor.h"
#include "core/dicom/series_reader.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/net/grpc/service_internal.h"
#include "server/net/grpc/status_map.h"
#include "spdlog/spdlog.h"

namespace interslice::server {

namespace service_internal {

absl::StatusOr<bool> ArtifactReader::Next(v1::ArtifactChunk* chunk) {
  if (!opened_) {
    in_.open(path_, std::ios::binary);
    if (!in_) return absl::DataLossError("an artifact is missing");
    in_.seekg(offset_);
    opened_ = true;
  } else if (offset_ >= info_.size_bytes()) {
    return false;
  }
  chunk->Clear();
  if (first_) *chunk->mutable_info() = info_;
  first_ = false;
  const int64_t n =
      std::min<int64_t>(chunk_bytes_, info_.size_bytes() - offset_);
  std::string* data = chunk->mutable_data();
  data->resize(static_cast<size_t>(n));
  in_.read(data->data(), n);
  if (in_.gcount() != n) return absl::DataLossError("an artifact is short");
  chunk->set_offset(offset_);
  offset_ += n;
  return true;
}

}  // namespace service_internal

UploadStreamLimits InterSliceService::upload_limits() const {
  UploadStreamLimits limits;
  limits.max_chunk_bytes = options_.max_chunk_bytes;
  limits.max_upload_bytes = manager_->options().max_upload_bytes;
  return limits;
}

absl::StatusOr<Caller> InterSliceService::Authenticate(
    grpc::CallbackServerContext* context) const {
  absl::StatusOr<Caller> caller = IdentifyCaller(auth_, *context);
  if (!caller.ok()) {
    spdlog::warn("refused a call from {}: missing or wrong bearer token",
                 LogSafe(context->peer()));
    AuditEvent e;
    e.event = "auth.refused";
    e.outcome = AuditOutcome::kMinorFailure;
    e.source = context->peer();
    e.detail = "missing or wrong bearer token";
    Audit(std::move(e));
  }
  return caller;
}

void InterSliceService::Audit(AuditEvent event) const {
  if (options_.audit != nullptr) options_.audit->Record(std::move(event));
}

std::optional<std::string> InterSliceService::ForwardTarget(
    const grpc::CallbackServerContext& context,
    const std::string& job_id) const {
  if (forwarder_ == nullptr || manager_->Find(job_id) != nullptr) {
    return std::nullopt;
  }
  return forwarder_->Route(context, job_id);
}

grpc::ServerUnaryReactor* InterSliceService::GetServerInfo(
    grpc::CallbackServerContext* context, const v1::ServerInfoRequest* request,
    v1::ServerInfo* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  response->set_version(options_.version);
  response->set_api("interslice.v1");
  for (const TransferSyntaxInfo& syntax : DecodableTransferSyntaxes()) {
    v1::TransferSyntax* t = response->add_transfer_syntaxes();
    t->set_uid(syntax.uid);
    t->set_name(syntax.name);
  }
  const ManagerOptions& m = manager_->options();
  v1::Limits* limits = response->mutable_limits();
  limits->set_max_upload_bytes(m.max_upload_bytes);
  limits->set_max_output_voxels(m.max_output_voxels);
  limits->set_max_queued_jobs(m.max_queued_jobs);
  limits->set_workers(m.workers);
  limits->set_threads_per_job(m.threads_per_job);
  limits->set_max_chunk_bytes(options_.max_chunk_bytes);
  limits->set_result_retention_seconds(m.retention_seconds);
  limits->set_spool_quota_bytes(spool_->quota_bytes());
  limits->set_max_concurrent_uploads(options_.uploads.max_concurrent);
  limits->set_max_uploads_per_client(options_.uploads.max_per_peer);
  limits->set_upload_idle_timeout_seconds(
      options_.uploads.idle_timeout_seconds);
  limits->set_upload_timeout_seconds(options_.uploads.total_timeout_seconds);
  for (const char* s : {"linear", "cg", "direct", "morph"})
    response->add_methods(s);
  for (const char* s : {"nii", "nrrd", "nii-uncompressed"}) {
    response->add_volume_formats(s);
  }
  for (const char* s : {"stl", "ply", "obj"}) response->add_mesh_formats(s);
  const auto* descriptor =
      v1::ServerInfo::descriptor()->file()->FindServiceByName("InterSlice");
  for (int i = 0; i < descriptor->method_count(); ++i) {
    response->add_rpcs(descriptor->method(i)->name());
  }
  response->set_auth_required(auth_.tokens_required());
  response->set_draining(manager_->draining());
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

}  // namespace interslice::server
