#include "client/remote/watch_command.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <thread>

#include "CLI/CLI.hpp"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "client/progress_display.h"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"
#include "job/wire.h"

namespace interslice::client::remote {
namespace {

// Watches until the job ends, reconnecting after transient failures. Fills
// `final` with the terminal status.
int WatchJob(const Connection& connection, const std::string& job_id,
             bool quiet, v1::JobStatus* final) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  ProgressDisplay display(stderr, !quiet);
  int64_t sequence = 0;
  int retries = 0;
  for (;;) {
    grpc::ClientContext context;
    connection.Authorize(context);
    v1::WatchRequest request;
    request.set_job_id(job_id);
    request.set_after_sequence(sequence);
    auto reader = stub->Watch(&context, request);
    v1::JobStatus status;
    while (reader->Read(&status)) {
      retries = 0;
      sequence = std::max(sequence, status.sequence());
      if (status.state() == v1::JOB_STATE_RUNNING ||
          status.state() == v1::JOB_STATE_QUEUED) {
        display.Update(ToEvent(status.progress()));
      }
      if (job::IsTerminalState(status.state())) *final = status;
    }
    const grpc::Status s = reader->Finish();
    if (s.ok() && job::IsTerminalState(final->state())) break;
    if (s.error_code() == grpc::UNAVAILABLE && ++retries <= kWatchRetries) {
      std::this_thread::sleep_for(std::chrono::seconds(1));
      continue;  // resume after `sequence`
    }
    display.Finish();
    return Fail(DescribeRpcError(s, connection.address()));
  }
  display.Finish();
  return 0;
}

bool HasPendingDelivery(const v1::JobStatus& status) {
  for (const v1::Delivery& d : status.deliveries()) {
    if (d.state() == v1::Delivery::PENDING) return true;
  }
  return false;
}

// The job's status now (the first message of a Watch).
absl::StatusOr<v1::JobStatus> CurrentStatus(const Connection& connection,
                                            const std::string& job_id) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 60);
  v1::WatchRequest request;
  request.set_job_id(job_id);
  auto reader = stub->Watch(&context, request);
  v1::JobStatus status;
  const bool got = reader->Read(&status);
  if (got) context.TryCancel();
  const grpc::Status s = reader->Finish();
  if (!got) {
    return absl::UnavailableError(DescribeRpcError(s, connection.address()));
  }
  return status;
}

}  // namespace

CLI::App* RegisterWatch(CLI::App& app, WatchArguments& args,
                        ConnectionOptions& connection) {
  CLI::App* watch = app.add_subcommand("watch",
                                       "Follow a detached job until it ends "
                                       "(reconnects after network failures)");
  watch->add_option("job", args.job_id, "Job id")->required();
  watch->add_flag("--quiet", args.quiet, "No progress display");
  watch->add_flag("--wait-deliveries", args.wait_deliveries,
                  "After the job, wait until its DICOM deliveries (send_to) "
                  "are delivered or failed; exit 1 if one failed");
  AddConnectionOptions(*watch, connection);
  return watch;
}

int RunWatch(const Connection& connection, const WatchArguments& args) {
  const std::string& job_id = args.job_id;
  v1::JobStatus final;
  if (int rc = WatchJob(connection, job_id, args.quiet, &final); rc != 0) {
    return rc;
  }
  if (final.state() != v1::JOB_STATE_SUCCEEDED) {
    return Fail(absl::StrCat("job ", job_id, " ", StateName(final.state()),
                             ": ", final.error_message()));
  }
  // Deliveries to DICOM peers go on after the job: poll until they end.
  while (args.wait_deliveries && HasPendingDelivery(final)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    absl::StatusOr<v1::JobStatus> now = CurrentStatus(connection, job_id);
    if (!now.ok()) return Fail(std::string(now.status().message()));
    final = *now;
  }
  if (!args.quiet) {
    std::printf(
        "job %s succeeded: %d artifact(s); get them with "
        "`interslice fetch %s --out DIR`\n",
        job_id.c_str(), final.artifacts_size(), job_id.c_str());
    for (const std::string& line : DescribeJob(final)) {
      std::printf("%s\n", line.c_str());
    }
    PrintDeliveries(final);
  }
  for (const v1::Delivery& d : final.deliveries()) {
    if (args.wait_deliveries && d.state() == v1::Delivery::FAILED) {
      return Fail(absl::StrCat("job ", job_id, ": delivery to ", d.peer(),
                               " failed: ", d.last_error()));
    }
  }
  return 0;
}

}  // namespace interslice::client::remote
