#include "client/remote/fetch_command.h"

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <thread>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "client/remote/artifacts.h"
#include "client/remote/remote_common.h"
#include "client/remote_commands.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {
namespace fs = std::filesystem;

CLI::App* RegisterFetch(CLI::App& app, FetchArguments& args,
                        ConnectionOptions& connection) {
  CLI::App* fetch = app.add_subcommand(
      "fetch", "Download a finished job's artifacts (resumes partial files)");
  fetch->add_option("job", args.job_id, "Job id")->required();
  fetch->add_option("--out", args.out, "Output folder")->required();
  fetch->add_option("--report", args.report, "Write the JSON report here");
  fetch->add_flag("--quiet", args.quiet, "No summary");
  AddConnectionOptions(*fetch, connection);
  return fetch;
}

int RunFetch(const Connection& connection, const FetchArguments& args) {
  const std::string& job_id = args.job_id;
  const std::string& out = args.out;
  auto stub = v1::InterSlice::NewStub(connection.channel());
  // The job's status: the first message of a Watch.
  v1::JobStatus status;
  {
    grpc::ClientContext context;
    connection.Authorize(context);
    SetTimeout(context, 60);
    v1::WatchRequest request;
    request.set_job_id(job_id);
    auto reader = stub->Watch(&context, request);
    const bool got = reader->Read(&status);
    // Only a stream still open needs cancelling; cancelling one that ended
    // would replace its status (NOT_FOUND, ...) with CANCELLED.
    if (got) context.TryCancel();
    const grpc::Status s = reader->Finish();
    if (!got) return Fail(DescribeRpcError(s, connection.address()));
  }
  if (status.state() != v1::JOB_STATE_SUCCEEDED) {
    return Fail(absl::StrCat("job ", job_id, " is ", StateName(status.state()),
                             status.error_message().empty()
                                 ? ""
                                 : absl::StrCat(": ", status.error_message())));
  }
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) return Fail("cannot create output folder " + out);
  int skipped = 0;
  for (const v1::ArtifactInfo& info : status.artifacts()) {
    // A complete file from an earlier fetch: keep it.
    if (IsSafeArtifactName(info.name()) &&
        IsCompleteArtifact((fs::path(out) / info.name()).string(), info)) {
      ++skipped;
      continue;
    }
    int attempts = 0;
    for (;;) {
      // Resume from what an earlier, interrupted fetch left behind.
      const std::string part = (fs::path(out) / info.name()).string() + ".part";
      int64_t offset = fs::exists(part, ec)
                           ? static_cast<int64_t>(fs::file_size(part, ec))
                           : 0;
      if (offset > info.size_bytes()) offset = 0;
      ArtifactFile file;
      if (absl::Status s = file.Begin(out, info, offset); !s.ok()) {
        return Fail(std::string(s.message()));
      }
      grpc::ClientContext context;
      connection.Authorize(context);
      v1::FetchRequest request;
      request.set_job_id(job_id);
      request.set_artifact_name(info.name());
      request.set_offset(offset);
      auto reader = stub->Fetch(&context, request);
      v1::ArtifactChunk chunk;
      absl::Status local = absl::OkStatus();
      while (local.ok() && reader->Read(&chunk))
        local = file.Append(chunk.data());
      if (!local.ok()) context.TryCancel();
      const grpc::Status s = reader->Finish();
      if (!local.ok()) return Fail(std::string(local.message()));
      if (s.ok()) {
        if (absl::Status c = file.Commit(); !c.ok()) {
          fs::remove(part, ec);
          return Fail(std::string(c.message()));
        }
        break;
      }
      if (s.error_code() == grpc::UNAVAILABLE && ++attempts <= kWatchRetries) {
        std::this_thread::sleep_for(std::chrono::seconds(1));
        continue;
      }
      return Fail(DescribeRpcError(s, connection.address()));
    }
  }
  if (!args.report.empty()) {
    if (absl::Status s = WriteReport(status.report_json(), out, args.report);
        !s.ok()) {
      return Fail(std::string(s.message()));
    }
  }
  if (!args.quiet) {
    const std::string kept =
        skipped > 0 ? absl::StrCat(" (", skipped, " already complete, kept)")
                    : "";
    std::printf("interslice: fetched %d file(s) of job %s to %s%s\n",
                status.artifacts_size() - skipped, job_id.c_str(), out.c_str(),
                kept.c_str());
    PrintRegion(status.report_json());
  }
  return 0;
}

}  // namespace interslice::client::remote
