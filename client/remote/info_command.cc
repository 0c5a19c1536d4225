#include "client/remote/info_command.h"

#include <cstdio>
#include <string>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {

CLI::App* RegisterInfo(CLI::App& app, ConnectionOptions& connection) {
  CLI::App* info =
      app.add_subcommand("info", "Show the server's version and limits");
  AddConnectionOptions(*info, connection);
  return info;
}

int RunInfo(const Connection& connection) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::ServerInfo info;
  const grpc::Status s =
      stub->GetServerInfo(&context, v1::ServerInfoRequest(), &info);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  const v1::Limits& l = info.limits();
  std::printf("interslice-server %s (%s)%s\n", info.version().c_str(),
              info.api().c_str(), info.draining() ? ", draining" : "");
  std::printf(
      "  workers %d x %d threads, queue %d, upload <= %lld bytes, "
      "output <= %lld voxels, chunk <= %d bytes\n",
      l.workers(), l.threads_per_job(), l.max_queued_jobs(),
      static_cast<long long>(l.max_upload_bytes()),
      static_cast<long long>(l.max_output_voxels()), l.max_chunk_bytes());
  std::printf(
      "  uploads <= %d at once (%d per client), idle timeout %g s, time "
      "limit %g s\n",
      l.max_concurrent_uploads(), l.max_uploads_per_client(),
      l.upload_idle_timeout_seconds(), l.upload_timeout_seconds());
  std::printf("  results kept %lld s, spool quota %lld bytes, auth %s\n",
              static_cast<long long>(l.result_retention_seconds()),
              static_cast<long long>(l.spool_quota_bytes()),
              info.auth_required() ? "required" : "off");
  std::string list;
  for (const auto& m : info.methods()) list += " " + m;
  std::printf("  methods:%s\n", list.c_str());
  list.clear();
  for (const auto& m : info.volume_formats()) list += " " + m;
  for (const auto& m : info.mesh_formats()) list += " " + m;
  std::printf("  outputs:%s\n", list.c_str());
  list.clear();
  for (const auto& m : info.rpcs()) list += " " + m;
  std::printf("  rpcs:%s\n", list.c_str());
  std::printf("  transfer syntaxes:\n");
  for (const auto& t : info.transfer_syntaxes()) {
    std::printf("    %s  %s\n", t.uid().c_str(), t.name().c_str());
  }
  return 0;
}

}  // namespace interslice::client::remote
