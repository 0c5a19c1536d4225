#include "server/net/dicomweb/pull.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "nlohmann/json.hpp"
#include "server/net/dicomweb/http.h"
#include "server/net/dicomweb/multipart.h"
#include "server/node/dataset_scan.h"
#include "server/node/peer.h"

namespace interslice::server::dicomweb {
namespace fs = std::filesystem;
namespace {

// A QIDO-RS answer lists each match with a handful of attributes: a few
// hundred bytes to a few KiB. Bounded per match, and absolutely.
constexpr size_t kQidoBytesPerMatch = 16384;
constexpr size_t kMaxQidoBytes = size_t{64} << 20;
// An answer that is not multipart (an error page) is read this far, then
// refused; its bytes are never kept.
constexpr size_t kMaxOtherAnswerBytes = size_t{1} << 20;
// Multipart headers of one part: a few lines.
constexpr int64_t kPartOverheadBytes = 16384;

size_t QidoLimit(int64_t matches) {
  return static_cast<size_t>(std::min<int64_t>(
      static_cast<int64_t>(kMaxQidoBytes),
      (matches + 1) * static_cast<int64_t>(kQidoBytesPerMatch)));
}

bool SyncPath(const std::string& path, bool directory) {
  const int fd =
      ::open(path.c_str(), directory ? O_RDONLY | O_DIRECTORY : O_RDONLY);
  if (fd < 0) return false;
  const bool ok = ::fsync(fd) == 0;
  ::close(fd);
  return ok;
}

// A QIDO-RS search: the matches (a JSON array of datasets; 204 is none).
absl::StatusOr<nlohmann::json> Qido(const node::DicomPeer& peer,
                                    const std::string& path_and_query,
                                    int64_t max_matches, int timeout_seconds) {
  absl::StatusOr<std::unique_ptr<HttpRequest>> made = HttpRequest::Make(
      peer, absl::StrCat(peer.web.url, path_and_query), timeout_seconds);
  if (!made.ok()) return made.status();
  HttpRequest& request = **made;
  request.AddHeader("Accept: application/dicom+json");
  const std::string what = absl::StrCat("QIDO-RS of ", node::PeerLabel(peer));
  BoundedBody answer(request, QidoLimit(max_matches), what);
  absl::StatusOr<long> http = request.Perform();
  if (!http.ok()) return http.status();
  if (*http == 204) return nlohmann::json::array();
  if (*http == 404) {
    return absl::NotFoundError(
        absl::StrCat(what, ": HTTP 404 (no such study or series)"));
  }
  if (*http != 200) return HttpStatusError(peer, "QIDO-RS", *http);
  nlohmann::json json = nlohmann::json::parse(answer.text(), nullptr, false);
  bool datasets = json.is_array();
  for (const nlohmann::json& item : datasets ? json : nlohmann::json()) {
    datasets = datasets && item.is_object();
  }
  if (!datasets || !IsDicomJson(request.content_type())) {
    return absl::FailedPreconditionError(absl::StrCat(
        what, ": HTTP 200 but not a DICOM JSON list (Content-Type '",
        request.content_type().substr(0, 64),
        "'): is url the base URL of a DICOMweb service?"));
  }
  return json;
}

// Writes each part of a WADO-RS answer to its own file in `dest`.
class PartWriter : public MultipartSink {
 public:
  PartWriter(std::string dest, int64_t expected, int64_t max_bytes)
      : dest_(std::move(dest)), expected_(expected), max_bytes_(max_bytes) {}
  ~PartWriter() override { Abandon(); }

  absl::Status BeginPart(const PartHeaders& headers) override {
    if (instances_ + 1 > expected_) {
      return absl::FailedPreconditionError(absl::StrCat(
          "the peer sends more instances than its QIDO-RS answer listed (",
          expected_, ")"));
    }
    if (const auto type = headers.find("content-type");
        type != headers.end() &&
        !absl::StartsWithIgnoreCase(type->second, "application/dicom")) {
      return absl::InvalidArgumentError(
          absl::StrCat("part ", instances_ + 1, " is '",
                       type->second.substr(0, 64), "', not application/dicom"));
    }
    path_ = (fs::path(dest_) / absl::StrFormat("pacs-%06d.dcm", instances_ + 1))
                .string();
    temp_ = path_ + ".part";
    fd_ = ::open(temp_.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
    if (fd_ < 0) {
      return absl::InternalError(
          "cannot write a retrieved instance to the job's folder");
    }
    return absl::OkStatus();
  }

  absl::Status PartBytes(std::string_view data) override {
    if (bytes_ + static_cast<int64_t>(data.size()) > max_bytes_) {
      return absl::ResourceExhaustedError(
          absl::StrCat("the series on the peer is larger than ", max_bytes_,
                       " bytes (the server's upload limit per job)"));
    }
    while (!data.empty()) {
      const ssize_t n = ::write(fd_, data.data(), data.size());
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        return absl::InternalError(
            "cannot write a retrieved instance to the job's folder");
      }
      data.remove_prefix(static_cast<size_t>(n));
      bytes_ += n;
    }
    return absl::OkStatus();
  }

  absl::Status EndPart() override {
    const bool synced = ::fsync(fd_) == 0;
    ::close(fd_);
    fd_ = -1;
    if (!synced) {
      return absl::InternalError("cannot sync a retrieved instance");
    }
    if (absl::StatusOr<node::DatasetScanResult> scan =
            node::ScanPart10File(temp_);
        !scan.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "an instance from the peer was refused: ", scan.status().message()));
    }
    std::error_code ec;
    fs::rename(temp_, path_, ec);
    if (ec) return absl::InternalError("cannot rename a retrieved instance");
    temp_.clear();
    ++instances_;
    return absl::OkStatus();
  }

  // The part being written is removed (a failed retrieval).
  void Abandon() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    if (!temp_.empty()) {
      std::error_code ec;
      fs::remove(temp_, ec);
      temp_.clear();
    }
  }

  int64_t instances() const { return instances_; }
  int64_t bytes() const { return bytes_; }

 private:
  const std::string dest_;
  const int64_t expected_;
  const int64_t max_bytes_;
  std::string path_, temp_;
  int fd_ = -1;
  int64_t instances_ = 0;
  int64_t bytes_ = 0;
};

std::string Query(const std::vector<std::pair<std::string, std::string>>& kv) {
  std::string out;
  for (const auto& [key, value] : kv) {
    if (value.empty()) continue;
    absl::StrAppend(&out, out.empty() ? "?" : "&", key, "=",
                    EscapePathSegment(value));
  }
  return out;
}

}  // namespace

absl::StatusOr<node::RetrieveResult> RetrieveSeriesWeb(
    const node::DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits, int timeout_seconds) {
  if (study_instance_uid.empty() || series_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "pacs_source needs study_instance_uid and series_instance_uid");
  }
  const std::string series_path =
      absl::StrCat("/studies/", EscapePathSegment(study_instance_uid),
                   "/series/", EscapePathSegment(series_instance_uid));
  // How many instances: the limit keeps an honest peer's answer small; a
  // peer that ignores it meets the byte bound.
  absl::StatusOr<nlohmann::json> listed = Qido(
      peer,
      absl::StrCat(series_path, "/instances?limit=", limits.max_instances + 1,
                   "&includefield=00080018"),
      limits.max_instances, timeout_seconds);
  if (!listed.ok()) {
    if (listed.status().code() == absl::StatusCode::kNotFound) {
      return absl::NotFoundError(absl::StrCat(
          node::PeerLabel(peer), " has no instance of the requested series"));
    }
    return listed.status();
  }
  const int64_t expected = static_cast<int64_t>(listed->size());
  if (expected == 0) {
    return absl::NotFoundError(absl::StrCat(
        node::PeerLabel(peer), " has no instance of the requested series"));
  }
  if (expected > limits.max_instances) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "the series on ", node::PeerLabel(peer), " has more than ",
        limits.max_instances, " instances (the server's limit per job)"));
  }

  absl::StatusOr<std::unique_ptr<HttpRequest>> made = HttpRequest::Make(
      peer, absl::StrCat(peer.web.url, series_path), timeout_seconds);
  if (!made.ok()) return made.status();
  HttpRequest& request = **made;
  request.AddHeader(
      "Accept: multipart/related; type=\"application/dicom\"; "
      "transfer-syntax=*");
  const std::string what = absl::StrCat("WADO-RS of ", node::PeerLabel(peer));
  PartWriter writer(dest_dir, expected, limits.max_bytes);
  MultipartLimits part_limits;
  part_limits.max_part_bytes = limits.max_bytes;
  // One more than listed, so that the extra part is reported as the lie it
  // is (PartWriter::BeginPart) rather than as a limit.
  part_limits.max_parts = expected + 1;
  part_limits.max_total_bytes =
      limits.max_bytes + (expected + 1) * kPartOverheadBytes;
  std::optional<MultipartParser> parser;
  // Not multipart (an error page, HTML): counted and dropped (never kept),
  // up to a bound past which the answer is refused.
  bool not_multipart = false;
  size_t other_bytes = 0;
  request.SetSink([&](const char* data, size_t n) {
    if (!parser.has_value() && !not_multipart) {
      absl::StatusOr<std::string> boundary =
          MultipartBoundary(request.content_type());
      if (boundary.ok()) {
        parser.emplace(*boundary, WadoResponseMultipart(part_limits), &writer);
      } else {
        not_multipart = true;
      }
    }
    if (not_multipart) {
      other_bytes += n;
      if (other_bytes > kMaxOtherAnswerBytes) {
        request.SetAbortStatus(absl::FailedPreconditionError(absl::StrCat(
            what, ": the answer is not multipart/related (Content-Type '",
            request.content_type().substr(0, 64), "')")));
        return false;
      }
      return true;
    }
    absl::Status s = parser->Feed(std::string_view(data, n));
    if (!s.ok()) {
      request.SetAbortStatus(
          absl::Status(s.code(), absl::StrCat(what, ": ", s.message())));
      return false;
    }
    return true;
  });
  absl::StatusOr<long> http = request.Perform();
  auto fail = [&](absl::Status status) {
    writer.Abandon();
    SyncPath(dest_dir, true);
    return status;
  };
  if (!http.ok()) return fail(http.status());
  if (*http == 404) {
    return fail(absl::NotFoundError(absl::StrCat(
        node::PeerLabel(peer), " has no instance of the requested series")));
  }
  if (*http != 200) return fail(HttpStatusError(peer, "WADO-RS", *http));
  if (!parser.has_value()) {
    return fail(absl::FailedPreconditionError(absl::StrCat(
        what, ": HTTP 200 but not multipart/related (Content-Type '",
        request.content_type().substr(0, 64), "')")));
  }
  if (absl::Status s = parser->Finish(); !s.ok()) {
    return fail(absl::Status(s.code(), absl::StrCat(what, ": ", s.message())));
  }
  SyncPath(dest_dir, true);
  if (writer.instances() != expected) {
    return absl::FailedPreconditionError(absl::StrCat(
        what, ": sent ", writer.instances(), " of the ", expected,
        " instances its QIDO-RS answer listed (a partial series is not "
        "used)"));
  }
  return node::RetrieveResult{writer.instances(), writer.bytes()};
}

absl::StatusOr<node::FindResult> FindStudiesAndSeriesWeb(
    const node::DicomPeer& peer, const node::FindQuery& query,
    const node::FindLimits& limits, int timeout_seconds) {
  if (absl::Status s = node::CheckFindQuery(query); !s.ok()) return s;
  node::FindResult result;
  absl::StatusOr<nlohmann::json> studies =
      Qido(peer,
           absl::StrCat("/studies",
                        Query({{"PatientID", query.patient_id},
                               {"StudyDate", query.study_date},
                               {"AccessionNumber", query.accession_number},
                               {"ModalitiesInStudy", query.modality},
                               {"limit", absl::StrCat(limits.max_studies + 1)},
                               {"includefield", "00081030"}})),
           limits.max_studies, timeout_seconds);
  if (!studies.ok()) return studies.status();
  for (const nlohmann::json& d : *studies) {
    if (static_cast<int>(result.studies.size()) >= limits.max_studies) {
      result.truncated = true;
      break;
    }
    node::FoundStudy study;
    study.study_instance_uid = DicomJsonText(d, "0020000D");
    study.patient_id = DicomJsonText(d, "00100020");
    study.study_date = DicomJsonText(d, "00080020");
    study.accession_number = DicomJsonText(d, "00080050");
    study.study_description = DicomJsonText(d, "00081030");
    study.modalities = DicomJsonText(d, "00080061");
    if (!study.study_instance_uid.empty()) {
      result.studies.push_back(std::move(study));
    }
  }
  int series_left = limits.max_series;
  for (node::FoundStudy& study : result.studies) {
    if (series_left <= 0) {
      result.truncated = true;
      break;
    }
    absl::StatusOr<nlohmann::json> series = Qido(
        peer,
        absl::StrCat("/studies/", EscapePathSegment(study.study_instance_uid),
                     "/series",
                     Query({{"Modality", query.modality},
                            {"limit", absl::StrCat(series_left + 1)},
                            {"includefield", "00201209"}})),
        series_left, timeout_seconds);
    if (!series.ok()) return series.status();
    for (const nlohmann::json& d : *series) {
      if (static_cast<int>(study.series.size()) >= series_left) {
        result.truncated = true;
        break;
      }
      node::FoundSeries s;
      s.series_instance_uid = DicomJsonText(d, "0020000E");
      s.modality = DicomJsonText(d, "00080060");
      s.series_number = DicomJsonText(d, "00200011");
      s.series_description = DicomJsonText(d, "0008103E");
      const nlohmann::json* count = DicomJsonValue(d, "00201209");
      if (count != nullptr && !count->empty()) {
        int64_t n = -1;
        if ((*count)[0].is_number_integer()) {
          n = (*count)[0].get<int64_t>();
        } else if ((*count)[0].is_string()) {
          n = std::atoll((*count)[0].get<std::string>().c_str());
        }
        s.instances = n;
      }
      if (!s.series_instance_uid.empty()) study.series.push_back(std::move(s));
    }
    series_left -= static_cast<int>(study.series.size());
  }
  return result;
}

}  // namespace interslice::server::dicomweb
