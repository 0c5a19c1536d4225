#include "client/remote/cancel_command.h"

#include <cstdio>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"
#include "job/wire.h"

namespace interslice::client::remote {

CLI::App* RegisterCancel(CLI::App& app, CancelArguments& args,
                         ConnectionOptions& connection) {
  CLI::App* cancel = app.add_subcommand("cancel", "Cancel a detached job");
  cancel->add_option("job", args.job_id, "Job id")->required();
  AddConnectionOptions(*cancel, connection);
  return cancel;
}

int RunCancel(const Connection& connection, const CancelArguments& args) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::CancelRequest request;
  request.set_job_id(args.job_id);
  v1::JobStatus status;
  const grpc::Status s = stub->Cancel(&context, request, &status);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  std::printf("job %s: %s%s\n", args.job_id.c_str(), StateName(status.state()),
              status.cancel_requested() && !job::IsTerminalState(status.state())
                  ? " (cancellation requested)"
                  : "");
  return 0;
}

}  // namespace interslice::client::remote
