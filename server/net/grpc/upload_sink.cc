// UploadSink (upload_sink.h): the disk side of an upload.
#include "server/net/grpc/upload_sink.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <filesystem>

#include "absl/strings/str_cat.h"

namespace interslice::server {
namespace fs = std::filesystem;

#define INTERSLICE_SINK_RETURN_IF_ERROR(expr) \
  do {                                        \
    absl::Status _s = (expr);                 \
    if (!_s.ok()) return _s;                  \
  } while (0)

absl::Status UploadSink::Consume(const v1::UploadRequest& message) {
  UploadStep step;
  INTERSLICE_SINK_RETURN_IF_ERROR(stream_.Next(message, &step));
  if (step.header) {
    absl::StatusOr<std::shared_ptr<Job>> job =
        manager_->Admit(stream_.header(), ephemeral_, deadline_, owner_);
    if (!job.ok()) return job.status();
    job_ = *job;
    // The kind Admit made says which uploads, if any, it takes by name (a
    // fill's segmentation and label names).
    named_ = job_->kind()->named_uploads();
    received_.assign(named_.size(), false);
    return absl::OkStatus();
  }
  if (step.open_file) {
    INTERSLICE_SINK_RETURN_IF_ERROR(
        OpenFile(step.file_index, message.chunk().file_name()));
  }
  if (!step.data.empty()) {
    INTERSLICE_SINK_RETURN_IF_ERROR(Write(step.offset, step.data));
  }
  if (step.close_file) INTERSLICE_SINK_RETURN_IF_ERROR(SyncAndCloseFile());
  return absl::OkStatus();
}

absl::Status UploadSink::Finish() {
  INTERSLICE_SINK_RETURN_IF_ERROR(stream_.Finish());
  for (size_t n = 0; n < named_.size(); ++n) {
    if (received_[n]) continue;
    // The client's file names may carry patient data: not echoed.
    return absl::InvalidArgumentError(absl::StrCat(
        named_[n].field, " names none of the ", stream_.header().file_count(),
        " uploaded files (compared exactly with FileChunk.file_name)"));
  }
  FsyncDir(spool_->UploadDir(job_->id()));
  metrics_->BytesIn(static_cast<double>(stream_.bytes_received()));
  absl::Status s = manager_->Enqueue(job_);
  if (s.ok()) enqueued_ = true;
  return s;
}

void UploadSink::Abort() {
  CloseFile();
  if (job_ && !enqueued_ && !aborted_) {
    aborted_ = true;
    manager_->Abandon(job_);
  }
}

void UploadSink::FsyncDir(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

absl::Status UploadSink::OpenFile(int index, const std::string& client_name) {
  CloseFile();
  // Index-based names: the client's names may carry patient data, and the
  // reader's error messages quote file names.
  char name[32];
  std::snprintf(name, sizeof(name), "%06d.dcm", index);
  std::string path = (fs::path(spool_->UploadDir(job_->id())) / name).string();
  // A file the job takes by name (a fill's segmentation, its label names)
  // goes where its kind says, out of the series' folder level.
  const auto named =
      std::find_if(named_.begin(), named_.end(),
                   [&](const auto& n) { return n.client_name == client_name; });
  if (named != named_.end()) {
    const size_t n = static_cast<size_t>(named - named_.begin());
    if (received_[n]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "two uploaded files carry the name given as ", named->field));
    }
    received_[n] = true;
    const fs::path target =
        fs::path(spool_->UploadDir(job_->id())) / named->path;
    std::error_code ec;
    fs::create_directories(target.parent_path(), ec);
    if (ec) return absl::InternalError("cannot create an upload folder");
    path = target.string();
  }
  fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd_ < 0) return absl::InternalError("cannot create an upload file");
  return absl::OkStatus();
}

absl::Status UploadSink::Write(int64_t offset, std::string_view data) {
  size_t done = 0;
  while (done < data.size()) {
    const ssize_t n =
        ::pwrite(fd_, data.data() + done, data.size() - done,
                 static_cast<off_t>(offset + static_cast<int64_t>(done)));
    if (n < 0) {
      if (errno == EINTR) continue;
      return absl::ResourceExhaustedError(
          "cannot write the upload to the spool (disk full?)");
    }
    done += static_cast<size_t>(n);
  }
  return absl::OkStatus();
}

absl::Status UploadSink::SyncAndCloseFile() {
  const bool synced = ::fsync(fd_) == 0;
  CloseFile();
  if (!synced) return absl::InternalError("cannot flush an upload file");
  return absl::OkStatus();
}

void UploadSink::CloseFile() {
  if (fd_ >= 0) {
    ::close(fd_);
    fd_ = -1;
  }
}

#undef INTERSLICE_SINK_RETURN_IF_ERROR

}  // namespace interslice::server
