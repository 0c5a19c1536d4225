#include "server/net/grpc/status_map.h"

#include "server/base/redact.h"

namespace interslice::server {

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()),
                      RedactPhi(status.message()));
}

}  // namespace interslice::server
