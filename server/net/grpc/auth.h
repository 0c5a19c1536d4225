// The caller of an RPC: Authenticator (server/base/identity.h) over gRPC's
// call metadata and peer certificate.
#ifndef INTERSLICE_SERVER_NET_GRPC_AUTH_H_
#define INTERSLICE_SERVER_NET_GRPC_AUTH_H_

#include "absl/status/statusor.h"
#include "grpcpp/server_context.h"
#include "server/base/identity.h"

namespace interslice::server {

// With tokens: the name of the token the call's "authorization" metadata
// carries ("Bearer <token>"), or UNAUTHENTICATED. Without: the verified
// client certificate's subject (mutual TLS), else "".
absl::StatusOr<Caller> IdentifyCaller(const Authenticator& auth,
                                      const grpc::ServerContextBase& context);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_AUTH_H_
