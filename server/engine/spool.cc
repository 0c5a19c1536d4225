#include "server/engine/spool.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <system_error>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "nlohmann/json.hpp"

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

namespace {

bool MadeByDicomListener(const JobRecord& record) {
  // Records of servers before JobOrigin carry only the origin text.
  return record.status().source().door() == v1::JobOrigin::DICOM ||
         absl::StartsWith(record.status().origin(), "dicom:");
}

}  // namespace

bool DeliversOnlyDicomToPeers(const JobRecord& record) {
  return MadeByDicomListener(record) && !record.spec().send_to().empty();
}

int64_t RemoveArtifactsNotAskedFor(const JobRecord& record,
                                   job::JobResult* result) {
  if (!DeliversOnlyDicomToPeers(record)) return 0;
  std::set<std::string> kinds;
  for (const Artifact& a : result->artifacts) kinds.insert(a.kind);
  const auto surplus = [&](const Artifact& a) {
    if (a.kind == "surface") {
      return absl::EndsWith(a.path, ".stl") &&
             kinds.count("surface-stl-dicom") != 0;
    }
    if (a.kind == "mask") return kinds.count("seg") != 0;
    if (a.kind == "distance") return kinds.count("distance-map") != 0;
    return false;
  };
  std::vector<Artifact> kept;
  std::set<std::string> removed_names;
  int64_t removed_bytes = 0;
  const auto remove = [&](const Artifact& a) {
    std::error_code ec;
    const fs::path path(a.path);
    int64_t bytes = TreeSize(a.path);  // a folder's files
    if (fs::is_regular_file(path, ec)) {
      bytes = static_cast<int64_t>(fs::file_size(path, ec));
    }
    fs::remove_all(path, ec);
    if (ec) return false;  // kept, and listed, when it cannot be removed
    removed_bytes += bytes;
    removed_names.insert(path.filename().string());
    return true;
  };
  bool mesh_file_kept = false;
  for (const Artifact& a : result->artifacts) {
    if (surplus(a) && remove(a)) continue;
    mesh_file_kept |= a.kind == "surface";
    kept.push_back(a);
  }
  // The note on mesh coordinates, once no mesh file is left to explain.
  if (!mesh_file_kept) {
    std::vector<Artifact> still;
    for (const Artifact& a : kept) {
      if (a.kind == "surface-coordinates" && remove(a)) continue;
      still.push_back(a);
    }
    kept = std::move(still);
  }
  if (removed_names.empty()) return 0;
  result->artifacts = std::move(kept);
  // The report lists the artifacts by bare file name (JobKind::UseSpool).
  nlohmann::ordered_json report = nlohmann::ordered_json::parse(
      result->report_json, nullptr, /*allow_exceptions=*/false);
  if (!report.is_discarded() && report.contains("artifacts") &&
      report["artifacts"].is_array()) {
    nlohmann::ordered_json artifacts = nlohmann::ordered_json::array();
    for (const auto& a : report["artifacts"]) {
      const bool gone =
          a.contains("path") && a["path"].is_string() &&
          removed_names.count(
              fs::path(a["path"].get<std::string>()).filename().string()) != 0;
      if (!gone) artifacts.push_back(a);
    }
    report["artifacts"] = std::move(artifacts);
    result->report_json =
        report.dump(2, ' ', false, nlohmann::json::error_handler_t::replace);
  }
  return removed_bytes;
}

}  // namespace interslice::server
