#include "client/remote/kept_commands.h"

#include <cstdio>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {

KeptSubcommands RegisterKept(CLI::App& app, KeptRerunArguments& rerun_args,
                             ConnectionOptions& connection) {
  CLI::App* kept = app.add_subcommand(
      "kept",
      "The series the server's DICOM listener holds (no rule matched, or "
      "their job was made), and running them again (admins only)");
  kept->require_subcommand(1);
  KeptSubcommands subcommands;
  subcommands.list = kept->add_subcommand(
      "list",
      "One line per series the node holds: id, state (receiving, "
      "incomplete, kept) and since when, AE titles, modality, instances, "
      "UIDs, why it is held");
  AddConnectionOptions(*subcommands.list, connection);
  subcommands.rerun = kept->add_subcommand(
      "rerun",
      "Match a kept series (or every one without a job) against the "
      "server's rules now and make its job; prints each job id");
  subcommands.rerun->add_option("id", rerun_args.id,
                                "A kept series' id (kept list)");
  subcommands.rerun->add_flag("--all-unmatched", rerun_args.all_unmatched,
                              "Every kept series no rule matched");
  AddConnectionOptions(*subcommands.rerun, connection);
  return subcommands;
}

absl::Status CheckKeptRerun(const KeptRerunArguments& args) {
  if (args.all_unmatched == !args.id.empty()) {
    return absl::InvalidArgumentError(
        "kept rerun: give a kept series' id or --all-unmatched");
  }
  return absl::OkStatus();
}

int RunKeptList(const Connection& connection) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 120);
  v1::ListKeptResponse response;
  const grpc::Status s =
      stub->ListKept(&context, v1::ListKeptRequest(), &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  for (const v1::ListKeptResponse::Series& k : response.series()) {
    // Servers before issue 39 listed kept series only, without a state.
    const std::string state = k.state().empty() ? "kept" : k.state();
    std::printf(
        "%s  %s %s  %s -> %s  %s  %lld instance(s)  study %s  series %s  "
        "%s\n",
        Printable(k.id()).c_str(), Printable(state).c_str(),
        UtcTime(k.kept_since_unix_ms()).c_str(),
        Printable(k.calling_ae()).c_str(), Printable(k.called_ae()).c_str(),
        k.modality().empty() ? "?" : Printable(k.modality()).c_str(),
        static_cast<long long>(k.instance_count()),
        Printable(k.study_instance_uid()).c_str(),
        Printable(k.series_instance_uid()).c_str(), Printable(k.why()).c_str());
  }
  if (response.series().empty()) std::fprintf(stderr, "no series is kept\n");
  return 0;
}

int RunKeptRerun(const Connection& connection, const KeptRerunArguments& args) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 600);
  v1::RerunKeptRequest request;
  request.set_id(args.id);
  request.set_all_unmatched(args.all_unmatched);
  v1::RerunKeptResponse response;
  const grpc::Status s = stub->RerunKept(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  for (const std::string& job : response.job_ids()) {
    std::printf("job %s\n", Printable(job).c_str());
  }
  for (const std::string& why : response.not_matched()) {
    std::printf("not matched %s\n", Printable(why).c_str());
  }
  if (args.all_unmatched && response.job_ids().empty() &&
      response.not_matched().empty()) {
    std::fprintf(stderr, "no kept series without a job\n");
  }
  return 0;
}

}  // namespace interslice::client::remote
