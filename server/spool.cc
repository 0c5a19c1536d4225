#include "server/spool.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <system_error>

#include "absl/strings/str_cat.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

absl::Status Errno(const std::string& what) {
  return absl::InternalError(absl::StrCat(what, ": ", std::strerror(errno)));
}

void FsyncDir(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

}  // namespace

absl::Status WriteFileAtomically(const std::string& path,
                                 const std::string& data) {
  const std::string tmp = path + ".tmp";
  const int fd =
      ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  if (fd < 0) return Errno("cannot create a spool file");
  size_t done = 0;
  while (done < data.size()) {
    const ssize_t n = ::write(fd, data.data() + done, data.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const absl::Status s = Errno("cannot write a spool file");
      ::close(fd);
      ::unlink(tmp.c_str());
      return s;
    }
    done += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0 || ::close(fd) != 0) {
    ::unlink(tmp.c_str());
    return Errno("cannot flush a spool file");
  }
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    ::unlink(tmp.c_str());
    return Errno("cannot rename a spool file");
  }
  FsyncDir(fs::path(path).parent_path().string());
  return absl::OkStatus();
}

int64_t TreeSize(const std::string& path) {
  std::error_code ec;
  int64_t total = 0;
  for (fs::recursive_directory_iterator it(path, ec), end; !ec && it != end;
       it.increment(ec)) {
    if (it->is_regular_file(ec)) {
      total += static_cast<int64_t>(it->file_size(ec));
    }
  }
  return total;
}

absl::StatusOr<std::unique_ptr<Spool>> Spool::Open(const std::string& root,
                                                   int64_t quota_bytes) {
  std::error_code ec;
  fs::create_directories(fs::path(root) / "jobs", ec);
  if (ec) {
    return absl::FailedPreconditionError(absl::StrCat(
        "cannot create the spool folder ", root, ": ", ec.message()));
  }
  ::chmod(root.c_str(), 0700);
  std::unique_ptr<Spool> spool(new Spool(root, quota_bytes));
  spool->used_ = TreeSize((fs::path(root) / "jobs").string());
  return spool;
}

std::string Spool::JobDir(const std::string& id) const {
  return (fs::path(root_) / "jobs" / id).string();
}
std::string Spool::UploadDir(const std::string& id) const {
  return (fs::path(JobDir(id)) / "upload").string();
}
std::string Spool::OutputDir(const std::string& id) const {
  return (fs::path(JobDir(id)) / "out").string();
}

absl::Status Spool::CreateJob(const std::string& id) {
  std::error_code ec;
  fs::create_directories(UploadDir(id), ec);
  if (!ec) fs::create_directories(OutputDir(id), ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create a job folder: ", ec.message()));
  }
  return absl::OkStatus();
}

absl::Status Spool::WriteRecord(const JobRecord& record) {
  std::string data;
  if (!record.SerializeToString(&data)) {
    return absl::InternalError("cannot serialise a job record");
  }
  return WriteFileAtomically(
      (fs::path(JobDir(record.status().job_id())) / "job.pb").string(), data);
}

absl::StatusOr<std::vector<JobRecord>> Spool::LoadRecords() {
  std::vector<JobRecord> records;
  std::error_code ec;
  std::vector<std::string> orphans;
  for (const fs::directory_entry& entry :
       fs::directory_iterator(fs::path(root_) / "jobs", ec)) {
    if (!entry.is_directory()) continue;
    const std::string id = entry.path().filename().string();
    std::ifstream in(entry.path() / "job.pb", std::ios::binary);
    JobRecord record;
    if (!in || !record.ParseFromIstream(&in) ||
        record.status().job_id() != id) {
      orphans.push_back(id);
      continue;
    }
    records.push_back(std::move(record));
  }
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot list the spool: ", ec.message()));
  }
  for (const std::string& id : orphans) RemoveJob(id);
  used_ = TreeSize((fs::path(root_) / "jobs").string());
  return records;
}

void Spool::RemoveJob(const std::string& id) {
  std::error_code ec;
  fs::remove_all(JobDir(id), ec);
}

void Spool::RemoveUploads(const std::string& id) {
  std::error_code ec;
  fs::remove_all(UploadDir(id), ec);
}

void Spool::RemoveOutputs(const std::string& id) {
  std::error_code ec;
  fs::remove_all(OutputDir(id), ec);
  fs::create_directories(OutputDir(id), ec);
}

bool Spool::TryReserve(int64_t bytes) {
  int64_t used = used_.load();
  do {
    if (used + bytes > quota_) return false;
  } while (!used_.compare_exchange_weak(used, used + bytes));
  return true;
}

void Spool::Release(int64_t bytes) { used_ -= bytes; }

bool Spool::FileSystemFull() const {
  struct statvfs fs;
  if (::statvfs(root_.c_str(), &fs) != 0) return false;
  return static_cast<uint64_t>(fs.f_bavail) * fs.f_frsize < (1u << 20);
}

}  // namespace interslice::server
