#include "server/net/dicomweb/client.h"

#include <algorithm>
#include <atomic>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "nlohmann/json.hpp"
#include "server/net/dicomweb/http.h"
#include "server/node/outcome.h"
#include "server/node/peer.h"
// osconfig.h must precede every other DCMTK header.

namespace interslice::server::dicomweb {
namespace fs = std::filesystem;
namespace {

// A store response lists the request's instances: a few hundred bytes each.
// Far more than any honest answer to a request of stow_max_instances.
constexpr size_t kMaxJsonResponseBytes = size_t{16} << 20;

// One request's files as a multipart/related body (RFC 2387; PS3.18 8.6.1.2
// for the DICOM media type), read piece by piece from the files.
class MultipartBody {
 public:
  MultipartBody(std::vector<std::string> files, std::vector<int64_t> sizes,
                std::string boundary)
      : files_(std::move(files)),
        sizes_(std::move(sizes)),
        boundary_(std::move(boundary)) {
    part_head_ = absl::StrCat("--", boundary_,
                              "\r\nContent-Type: application/dicom\r\n\r\n");
    tail_ = absl::StrCat("--", boundary_, "--\r\n");
  }

  int64_t size() const {
    int64_t total = static_cast<int64_t>(tail_.size());
    for (int64_t s : sizes_) {
      total += static_cast<int64_t>(part_head_.size()) + s + 2;  // "\r\n"
    }
    return total;
  }

  // Fills `buffer`; -1 when a file cannot be read or is not as long as it
  // was (then error() says which).
  int64_t Read(char* buffer, size_t n) {
    size_t filled = 0;
    while (filled < n && !done_) {
      if (part_ == files_.size()) {
        filled += Copy(tail_, buffer + filled, n - filled);
        if (offset_ == tail_.size()) done_ = true;
        continue;
      }
      switch (stage_) {
        case Stage::kHead:
          filled += Copy(part_head_, buffer + filled, n - filled);
          if (offset_ == part_head_.size()) Next(Stage::kFile);
          break;
        case Stage::kFile: {
          if (!in_.is_open()) {
            in_.open(files_[part_], std::ios::binary);
            if (!in_.is_open()) return Fail("cannot be read");
          }
          const int64_t left = sizes_[part_] - static_cast<int64_t>(offset_);
          const size_t want =
              static_cast<size_t>(std::min<int64_t>(left, n - filled));
          in_.read(buffer + filled, static_cast<std::streamsize>(want));
          const size_t got = static_cast<size_t>(in_.gcount());
          if (got != want) return Fail("changed while it was being sent");
          filled += got;
          offset_ += got;
          if (static_cast<int64_t>(offset_) == sizes_[part_]) {
            in_.close();
            Next(Stage::kEnd);
          }
          break;
        }
        case Stage::kEnd:
          filled += Copy("\r\n", buffer + filled, n - filled);
          if (offset_ == 2) {
            ++part_;
            Next(Stage::kHead);
          }
          break;
      }
    }
    return static_cast<int64_t>(filled);
  }

  const absl::Status& error() const { return error_; }

 private:
  enum class Stage { kHead, kFile, kEnd };

  size_t Copy(absl::string_view text, char* out, size_t room) {
    const size_t n = std::min(room, text.size() - offset_);
    std::memcpy(out, text.data() + offset_, n);
    offset_ += n;
    return n;
  }
  void Next(Stage stage) {
    stage_ = stage;
    offset_ = 0;
  }
  int64_t Fail(const char* what) {
    error_ = absl::InvalidArgumentError(absl::StrCat(
        "cannot send ", fs::path(files_[part_]).filename().string(), ": it ",
        what));
    return -1;
  }

  const std::vector<std::string> files_;
  const std::vector<int64_t> sizes_;
  const std::string boundary_;
  std::string part_head_, tail_;
  size_t part_ = 0;
  Stage stage_ = Stage::kHead;
  size_t offset_ = 0;
  bool done_ = false;
  std::ifstream in_;
  absl::Status error_;
};

std::string RandomBoundary() {
  // 128 random bits: a DICOM file holding this line by chance is not a
  // practical concern (RFC 2046 5.1.1 asks only that it not occur).
  std::random_device random;
  std::string boundary = "interslice-";
  for (int i = 0; i < 4; ++i) {
    absl::StrAppendFormat(&boundary, "%08x", random());
  }
  return boundary;
}

std::string FailureText(const nlohmann::json& failed_item) {
  const nlohmann::json* reason = DicomJsonValue(failed_item, "00081197");
  if (reason == nullptr || reason->empty() ||
      !(*reason)[0].is_number_integer()) {
    return "refused (no Failure Reason given)";
  }
  const int code = (*reason)[0].get<int>();
  return absl::StrFormat("0x%04X %s", code,
                         node::CStoreStatusText(static_cast<uint16_t>(code)));
}

// One STOW-RS request for `files` (sizes known).
absl::StatusOr<node::StoreResult> PostStowBatch(
    const node::DicomPeer& peer, const std::vector<std::string>& files,
    const std::vector<int64_t>& sizes, const StowClientOptions& options) {
  const std::string what = absl::StrCat("STOW-RS to ", node::PeerLabel(peer));
  absl::StatusOr<std::unique_ptr<HttpRequest>> made = HttpRequest::Make(
      peer, absl::StrCat(peer.web.url, "/studies"), options.timeout_seconds);
  if (!made.ok()) return made.status();
  HttpRequest& request = **made;
  const std::string boundary = RandomBoundary();
  MultipartBody body(files, sizes, boundary);
  request.AddHeader(absl::StrCat(
      "Content-Type: multipart/related; type=\"application/dicom\"; "
      "boundary=",
      boundary));
  request.AddHeader("Accept: application/dicom+json");
  request.SetPostBody(
      [&](char* buffer, size_t n) {
        const int64_t got = body.Read(buffer, n);
        if (got < 0) request.SetAbortStatus(body.error());
        return got;
      },
      body.size());
  BoundedBody answer(request, kMaxJsonResponseBytes, what);
  absl::StatusOr<long> http = request.Perform();
  if (!http.ok()) return http.status();
  if (*http != 200 && *http != 202 && *http != 409) {
    return HttpStatusError(peer, "STOW-RS", *http);
  }
  nlohmann::json json = nlohmann::json::parse(answer.text(), nullptr, false);
  // PS3.18 10.5.3.2: the Store Instances Response Module, a DICOM JSON
  // dataset (some servers send it as an array of one).
  if (json.is_array() && json.size() == 1) json = json[0];
  const nlohmann::json* referenced = DicomJsonValue(json, "00081199");
  const nlohmann::json* failed = DicomJsonValue(json, "00081198");
  if (!json.is_object() || !IsDicomJson(request.content_type()) ||
      // Either sequence present, empty or not (an all-refused request may
      // carry an empty Referenced SOP Sequence and nothing else).
      (!json.contains("00081199") && !json.contains("00081198") &&
       *http != 409)) {
    return absl::FailedPreconditionError(
        absl::StrCat(what, ": HTTP ", *http,
                     " without a DICOM JSON store response (Content-Type '",
                     request.content_type().substr(0, 64),
                     "'): is url the base URL of a DICOMweb service?"));
  }
  const int total = static_cast<int>(files.size());
  node::StoreResult result;
  // A peer that lists more than it was sent is not believed beyond that.
  result.accepted = std::min<int>(
      total, referenced == nullptr ? 0 : static_cast<int>(referenced->size()));
  result.refused =
      std::min<int>(total - result.accepted,
                    failed == nullptr ? 0 : static_cast<int>(failed->size()));
  if (failed != nullptr && !failed->empty()) {
    result.first_refusal = FailureText((*failed)[0]);
  }
  const int unconfirmed = total - result.accepted - result.refused;
  if (unconfirmed > 0) {
    result.refused += unconfirmed;
    if (result.first_refusal.empty()) {
      result.first_refusal = absl::StrCat(
          unconfirmed,
          " instance(s) not confirmed by the store response (HTTP ", *http,
          ")");
    }
  }
  return result;
}

}  // namespace

absl::Status ProbeDicomWebPeer(const node::DicomPeer& peer,
                               int timeout_seconds) {
  absl::StatusOr<std::unique_ptr<HttpRequest>> made = HttpRequest::Make(
      peer, absl::StrCat(peer.web.url, "/studies?limit=1"), timeout_seconds);
  if (!made.ok()) return made.status();
  HttpRequest& request = **made;
  request.AddHeader("Accept: application/dicom+json");
  const std::string what = absl::StrCat("QIDO-RS of ", node::PeerLabel(peer));
  BoundedBody answer(request, kMaxJsonResponseBytes, what);
  absl::StatusOr<long> http = request.Perform();
  if (!http.ok()) return http.status();
  if (*http == 204) return absl::OkStatus();
  if (*http != 200) return HttpStatusError(peer, "QIDO-RS", *http);
  const nlohmann::json json =
      nlohmann::json::parse(answer.text(), nullptr, false);
  if (!json.is_array() || !IsDicomJson(request.content_type())) {
    return absl::FailedPreconditionError(absl::StrCat(
        what, ": HTTP 200 but not a DICOM JSON answer (Content-Type '",
        request.content_type().substr(0, 64),
        "'): is url the base URL of a DICOMweb service?"));
  }
  return absl::OkStatus();
}

absl::StatusOr<node::StoreResult> StowFiles(
    const node::DicomPeer& peer, const std::vector<std::string>& files,
    const StowClientOptions& options) {
  // Sizes and the Part 10 preamble first: a file that is not DICOM fails
  // the call before anything is sent (as the DIMSE path does).
  std::vector<int64_t> sizes;
  sizes.reserve(files.size());
  for (const std::string& file : files) {
    std::ifstream in(file, std::ios::binary);
    char magic[132] = {};
    std::error_code ec;
    const auto size = fs::file_size(file, ec);
    if (ec || !in.read(magic, sizeof(magic)) ||
        std::memcmp(magic + 128, "DICM", 4) != 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot send ", fs::path(file).filename().string(),
                       ": not a readable DICOM Part 10 file"));
    }
    sizes.push_back(static_cast<int64_t>(size));
  }
  // Requests: consecutive files up to the instance and byte bounds.
  struct Batch {
    std::vector<std::string> files;
    std::vector<int64_t> sizes;
    int64_t bytes = 0;
  };
  std::vector<Batch> batches;
  // Requests small enough that every lane gets some (two each, so that a
  // lane that finishes early takes another), within the configured bound:
  // a PACS parses one request's instances one after another, so 56 files
  // in requests of 50 and 6 kept one lane busy and the other idle.
  const int lanes_wanted = std::max(1, peer.max_associations);
  const int balanced = static_cast<int>((files.size() + 2 * lanes_wanted - 1) /
                                        (2 * lanes_wanted));
  const int max_instances =
      std::clamp(balanced, 1, std::max(1, options.stow_max_instances));
  for (size_t i = 0; i < files.size(); ++i) {
    if (batches.empty() ||
        static_cast<int>(batches.back().files.size()) >= max_instances ||
        (batches.back().bytes + sizes[i] > options.stow_max_bytes &&
         !batches.back().files.empty())) {
      batches.emplace_back();
    }
    batches.back().files.push_back(files[i]);
    batches.back().sizes.push_back(sizes[i]);
    batches.back().bytes += sizes[i];
  }
  const size_t lanes = std::min<size_t>(
      batches.size(), static_cast<size_t>(std::max(1, peer.max_associations)));
  std::vector<absl::StatusOr<node::StoreResult>> results(batches.size(),
                                                         node::StoreResult{});
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t b = next++; b < batches.size(); b = next++) {
      results[b] =
          PostStowBatch(peer, batches[b].files, batches[b].sizes, options);
      // After a transport failure the other requests would most likely
      // fail too: stop taking new ones (the queue retries everything).
      if (!results[b].ok() &&
          results[b].status().code() == absl::StatusCode::kUnavailable) {
        next = batches.size();
      }
    }
  };
  if (lanes <= 1) {
    work();
  } else {
    std::vector<std::thread> threads;
    threads.reserve(lanes);
    for (size_t lane = 0; lane < lanes; ++lane) threads.emplace_back(work);
    for (std::thread& t : threads) t.join();
  }
  node::StoreResult total;
  for (const absl::StatusOr<node::StoreResult>& r : results) {
    if (!r.ok()) return r.status();  // the first batch's error, in order
    total.accepted += r->accepted;
    total.refused += r->refused;
    if (total.first_refusal.empty()) total.first_refusal = r->first_refusal;
  }
  return total;
}

}  // namespace interslice::server::dicomweb
