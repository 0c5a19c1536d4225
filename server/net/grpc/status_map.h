// The one place where absl::Status becomes grpc::Status (every RPC's error
// passes here), its message scrubbed of patient data (server/base/redact.h).
#ifndef INTERSLICE_SERVER_NET_GRPC_STATUS_MAP_H_
#define INTERSLICE_SERVER_NET_GRPC_STATUS_MAP_H_

#include "absl/status/status.h"
#include "grpcpp/support/status.h"

namespace interslice::server {

// absl and gRPC share the canonical code numbering, so codes map one to one;
// the message is passed through RedactPhi.
grpc::Status ToGrpcStatus(const absl::Status& status);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_STATUS_MAP_H_
