#include "client/remote/health_command.h"

#include <cstdio>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "grpc/health/v1/health.grpc.pb.h"

namespace interslice::client::remote {

CLI::App* RegisterHealth(CLI::App& app, ConnectionOptions& connection) {
  CLI::App* health = app.add_subcommand(
      "health", "Check the server's health (exit 0 only when SERVING)");
  AddConnectionOptions(*health, connection);
  return health;
}

int RunHealth(const Connection& connection) {
  auto stub = grpc::health::v1::Health::NewStub(connection.channel());
  grpc::ClientContext context;
  SetTimeout(context, 10);
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  const grpc::Status s = stub->Check(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  const bool serving =
      response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
  std::printf("%s\n", grpc::health::v1::HealthCheckResponse::ServingStatus_Name(
                          response.status())
                          .c_str());
  return serving ? 0 : 1;
}

}  // namespace interslice::client::remote
