#include "client/remote/artifacts.h"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "client/remote_commands.h"
#include "job/job.h"
#include "nlohmann/json.hpp"

namespace interslice::client {

// Declared in client/remote_commands.h (the tests hold it there).
// Artifact names come from the server and become local paths: a file name,
// or "<folder>/<file>" (derived DICOM series), of plain characters only, so
// no name can climb out of the output folder or be absolute.
bool IsSafeArtifactName(const std::string& name) {
  const size_t slash = name.find('/');
  if (slash != std::string::npos &&
      name.find('/', slash + 1) != std::string::npos) {
    return false;
  }
  auto safe_component = [](std::string_view c) {
    if (c.empty() || c == "." || c == "..") return false;
    for (char ch : c) {
      if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '.' ||
            ch == '_' || ch == '-')) {
        return false;
      }
    }
    return true;
  };
  const std::string_view view(name);
  if (slash == std::string::npos) return safe_component(view);
  return safe_component(view.substr(0, slash)) &&
         safe_component(view.substr(slash + 1));
}

namespace remote {
namespace fs = std::filesystem;

std::string HashFile(const std::string& path) {
  absl::StatusOr<std::string> sha = Sha256OfFile(path);
  return sha.ok() ? *sha : std::string();
}

absl::Status ArtifactFile::Begin(const std::string& dir,
                                 const v1::ArtifactInfo& info, int64_t offset) {
  info_ = info;
  if (!IsSafeArtifactName(info.name())) {
    return absl::DataLossError("the server sent a bad artifact name");
  }
  final_ = (fs::path(dir) / info.name()).string();
  part_ = final_ + ".part";
  std::error_code ec;
  fs::create_directories(fs::path(final_).parent_path(), ec);
  if (ec) return absl::PermissionDeniedError("cannot create " + final_);
  // The digest is computed from the bytes as they arrive (no second read
  // of the file); a resumed fetch first hashes the part already on disk.
  hash_ = std::make_unique<Sha256>();
  if (offset > 0) {
    std::ifstream in(part_, std::ios::binary);
    std::vector<char> buffer(1 << 16);
    int64_t left = offset;
    while (in && left > 0) {
      in.read(buffer.data(), static_cast<std::streamsize>(
                                 std::min<int64_t>(left, buffer.size())));
      hash_->Update(std::string_view(buffer.data(), in.gcount()));
      left -= in.gcount();
    }
    if (left != 0) return absl::DataLossError("cannot read " + part_);
  }
  bytes_ = offset;
  out_.open(part_, offset > 0 ? std::ios::binary | std::ios::app
                              : std::ios::binary | std::ios::trunc);
  if (!out_) return absl::PermissionDeniedError("cannot write " + part_);
  return absl::OkStatus();
}

absl::Status ArtifactFile::Append(const std::string& data) {
  out_.write(data.data(), static_cast<std::streamsize>(data.size()));
  if (!out_) return absl::ResourceExhaustedError("cannot write " + part_);
  hash_->Update(data);
  bytes_ += static_cast<int64_t>(data.size());
  return absl::OkStatus();
}

absl::Status ArtifactFile::Commit() {
  out_.close();
  std::error_code ec;
  const auto size = fs::file_size(part_, ec);
  if (!out_ || ec || static_cast<int64_t>(size) != info_.size_bytes() ||
      bytes_ != info_.size_bytes() || hash_->Finish() != info_.sha256()) {
    return absl::DataLossError(absl::StrCat(
        info_.name(), ": size or SHA-256 does not match the server's"));
  }
  fs::rename(part_, final_, ec);
  if (ec) return absl::PermissionDeniedError("cannot rename " + part_);
  return absl::OkStatus();
}

bool IsCompleteArtifact(const std::string& path, const v1::ArtifactInfo& info) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) return false;
  const auto size = fs::file_size(path, ec);
  return !ec && static_cast<int64_t>(size) == info.size_bytes() &&
         HashFile(path) == info.sha256();
}

absl::Status WriteReport(const std::string& report_json,
                         const std::string& out_dir, const std::string& path) {
  nlohmann::ordered_json j =
      nlohmann::ordered_json::parse(report_json, nullptr, false);
  if (j.is_discarded()) return absl::DataLossError("the report is not JSON");
  if (j.contains("artifacts")) {
    for (auto& a : j["artifacts"]) {
      a["path"] = (fs::path(out_dir) / a["path"].get<std::string>()).string();
    }
  }
  std::ofstream file(path);
  file << j.dump(2) << "\n";
  file.close();
  if (!file) return absl::PermissionDeniedError("cannot write report " + path);
  return absl::OkStatus();
}

void PrintRegion(const std::string& report_json) {
  if (report_json.empty()) return;
  absl::StatusOr<JobReport> report = JobReportFromJson(report_json);
  if (!report.ok()) return;
  if (std::optional<std::string> line = job::RegionSummaryLine(*report)) {
    std::printf("%s\n", line->c_str());
  }
}

}  // namespace remote
}  // namespace interslice::client
