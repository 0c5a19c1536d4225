#include "server/net/grpc/auth.h"

#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include "grpc/grpc_security_constants.h"

namespace interslice::server {

absl::StatusOr<Caller> IdentifyCaller(const Authenticator& auth,
                                      const grpc::ServerContextBase& context) {
  std::string identity;
  if (auth.tokens_required()) {
    const auto& metadata = context.client_metadata();
    auto it = metadata.find("authorization");
    std::optional<std::string> name;
    if (it != metadata.end()) {
      name = auth.MatchBearer(
          std::string_view(it->second.data(), it->second.size()));
    }
    if (!name.has_value()) {
      return absl::UnauthenticatedError("missing or invalid bearer token");
    }
    identity = std::move(*name);
  } else if (const auto peer = context.auth_context();
             peer != nullptr && peer->IsPeerAuthenticated()) {
    // gRPC sets these only for a certificate the server verified.
    for (const char* property :
         {GRPC_X509_SUBJECT_PROPERTY_NAME, GRPC_X509_CN_PROPERTY_NAME}) {
      const auto values = peer->FindPropertyValues(property);
      if (values.empty()) continue;
      identity.assign(values.front().data(), values.front().size());
      if (property == std::string_view(GRPC_X509_CN_PROPERTY_NAME)) {
        identity = "CN=" + identity;
      }
      break;
    }
  }
  return auth.CallerOf(std::move(identity));
}

}  // namespace interslice::server
