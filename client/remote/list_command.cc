#include "client/remote/list_command.h"

#include <cstdio>
#include <string>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {

CLI::App* RegisterList(CLI::App& app, ListArguments& args,
                       ConnectionOptions& connection) {
  CLI::App* list =
      app.add_subcommand("list", "List the server's detached jobs");
  list->add_flag("--all", args.all, "Include finished jobs");
  AddConnectionOptions(*list, connection);
  return list;
}

int RunList(const Connection& connection, const ListArguments& args) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::ListRequest request;
  request.set_include_finished(args.all);
  v1::ListResponse response;
  const grpc::Status s = stub->List(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  // Labels are free text from whoever submitted (an admin lists everyone's):
  // Printable.
  for (const v1::JobStatus& j : response.jobs()) {
    std::printf("%s  %-9s  %-8s %5.1f%%  %s\n", j.job_id().c_str(),
                StateName(j.state()), j.progress().stage().c_str(),
                j.progress().stage_percent(), Printable(j.label()).c_str());
    for (const std::string& line : DescribeJob(j)) {
      std::printf("%s\n", line.c_str());
    }
    PrintDeliveries(j);
  }
  return 0;
}

}  // namespace interslice::client::remote
