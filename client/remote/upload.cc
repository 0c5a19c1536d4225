#include "client/remote/upload.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "client/progress_display.h"
#include "client/remote/artifacts.h"
#include "client/remote/remote_common.h"
#include "core/dicom/series_reader.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {
namespace fs = std::filesystem;
namespace {

constexpr size_t kChunkBytes = 64 * 1024;

// Sends the header and every file; false as soon as the stream breaks (the
// caller then reads the status from Finish()).
template <typename Writer>
bool Upload(Writer& writer, const v1::UploadHeader& header,
            const std::vector<LocalFile>& files) {
  v1::UploadRequest request;
  *request.mutable_header() = header;
  if (!writer.Write(request)) return false;
  std::vector<char> buffer(kChunkBytes);
  for (size_t i = 0; i < files.size(); ++i) {
    std::ifstream in(files[i].path, std::ios::binary);
    const std::string sha = HashFile(files[i].path);
    int64_t offset = 0;
    bool first = true;
    while (first || offset < files[i].size) {
      const int64_t n = std::min<int64_t>(kChunkBytes, files[i].size - offset);
      in.read(buffer.data(), n);
      request.Clear();
      v1::FileChunk* chunk = request.mutable_chunk();
      chunk->set_file_index(static_cast<int>(i));
      if (first) {
        chunk->set_file_name(files[i].name);
        chunk->set_file_size(files[i].size);
        chunk->set_sha256(sha);
      }
      chunk->set_offset(offset);
      chunk->set_data(buffer.data(), static_cast<size_t>(in.gcount()));
      if (!writer.Write(request)) return false;
      offset += in.gcount();
      first = false;
      if (in.gcount() == 0) break;
    }
  }
  return true;
}

}  // namespace

absl::StatusOr<std::vector<LocalFile>> CollectFiles(
    const std::vector<std::string>& inputs) {
  absl::StatusOr<std::vector<std::string>> paths = CollectInputFiles(inputs);
  if (!paths.ok()) return paths.status();
  std::vector<LocalFile> files;
  for (const std::string& path : *paths) {
    std::error_code ec;
    const auto size = fs::file_size(path, ec);
    if (ec) return absl::NotFoundError("cannot read an input file's size");
    files.push_back(
        {path, fs::path(path).filename().string(), static_cast<int64_t>(size)});
  }
  if (files.empty()) return absl::NotFoundError("no input files found");
  return files;
}

int InterpolateCall(const Connection& connection,
                    const v1::UploadHeader& header,
                    const std::vector<LocalFile>& files, const std::string& out,
                    const std::string& report, bool quiet,
                    double deadline_seconds) {
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) return Fail("cannot create output folder " + out);

  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  if (deadline_seconds > 0) SetTimeout(context, deadline_seconds);
  auto stream = stub->Interpolate(&context);
  if (Upload(*stream, header, files)) stream->WritesDone();

  ProgressDisplay display(stderr, !quiet);
  v1::InterpolateResponse response;
  ArtifactFile artifact;
  absl::Status local = absl::OkStatus();
  std::string job_id;
  v1::JobSummary summary;
  bool have_summary = false;
  while (stream->Read(&response)) {
    if (response.has_accepted()) {
      job_id = response.accepted().job_id();
    } else if (response.has_progress()) {
      display.Update(ToEvent(response.progress()));
    } else if (response.has_artifact() && local.ok()) {
      const v1::ArtifactChunk& chunk = response.artifact();
      if (chunk.has_info()) {
        if (artifact.open()) local = artifact.Commit();
        if (local.ok()) local = artifact.Begin(out, chunk.info(), 0);
      }
      if (local.ok()) local = artifact.Append(chunk.data());
    } else if (response.has_summary()) {
      if (artifact.open() && local.ok()) local = artifact.Commit();
      summary = response.summary();
      have_summary = true;
    }
    if (!local.ok()) context.TryCancel();
  }
  const grpc::Status status = stream->Finish();
  display.Finish();
  if (!local.ok()) return Fail(std::string(local.message()));
  if (!status.ok()) {
    if (artifact.open()) fs::remove(artifact.part_path(), ec);
    return Fail(DescribeRpcError(status, connection.address()));
  }
  if (!have_summary) return Fail("the server ended the call without a summary");
  if (!report.empty()) {
    if (absl::Status s = WriteReport(summary.report_json(), out, report);
        !s.ok()) {
      return Fail(std::string(s.message()));
    }
  }
  if (!quiet) {
    std::printf("interslice: wrote %d file(s) to %s (job %s on %s)\n",
                summary.artifacts_size(), out.c_str(), job_id.c_str(),
                connection.address().c_str());
    for (const v1::ArtifactInfo& a : summary.artifacts()) {
      std::printf("  %-9s %s (%lld bytes)\n", a.kind().c_str(),
                  (fs::path(out) / a.name()).string().c_str(),
                  static_cast<long long>(a.size_bytes()));
    }
    PrintRegion(summary.report_json());
  }
  return 0;
}

int SubmitCall(const Connection& connection, const v1::UploadHeader& header,
               const std::vector<LocalFile>& files) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  v1::SubmitResponse response;
  auto writer = stub->Submit(&context, &response);
  if (Upload(*writer, header, files)) writer->WritesDone();
  const grpc::Status status = writer->Finish();
  if (!status.ok()) return Fail(DescribeRpcError(status, connection.address()));
  std::printf("%s\n", response.job_id().c_str());
  return 0;
}

}  // namespace interslice::client::remote
