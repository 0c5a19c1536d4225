#include "tests/testing/fake_peer.h"

#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"

namespace interslice::testing {

namespace node = server::node;
namespace fs = std::filesystem;

void FakePeerClient::QueueStoreAnswer(
    absl::StatusOr<node::StoreResult> answer) {
  std::lock_guard<std::mutex> lock(mu_);
  store_answers_.push_back(std::move(answer));
}

void FakePeerClient::SetEcho(absl::Status status) {
  std::lock_guard<std::mutex> lock(mu_);
  echo_ = std::move(status);
}

void FakePeerClient::SetSeries(std::vector<std::string> files,
                               absl::Status error) {
  std::lock_guard<std::mutex> lock(mu_);
  series_ = std::move(files);
  series_error_ = std::move(error);
}

void FakePeerClient::SetFind(absl::StatusOr<node::FindResult> result) {
  std::lock_guard<std::mutex> lock(mu_);
  find_ = std::move(result);
}

std::vector<std::vector<std::string>> FakePeerClient::stored() const {
  std::lock_guard<std::mutex> lock(mu_);
  return stored_;
}

absl::Status FakePeerClient::Echo() {
  std::lock_guard<std::mutex> lock(mu_);
  return echo_;
}

absl::StatusOr<node::FindResult> FakePeerClient::Find(
    const node::FindQuery& query, const node::FindLimits& limits) {
  if (absl::Status s = node::CheckFindQuery(query); !s.ok()) return s;
  std::lock_guard<std::mutex> lock(mu_);
  if (!find_.ok()) return find_.status();
  node::FindResult result = *find_;
  if (static_cast<int>(result.studies.size()) > limits.max_studies) {
    result.studies.resize(static_cast<size_t>(limits.max_studies));
    result.truncated = true;
  }
  return result;
}

absl::StatusOr<node::RetrieveResult> FakePeerClient::Retrieve(
    const std::string& /*study_instance_uid*/,
    const std::string& /*series_instance_uid*/, const std::string& dest_dir,
    const node::RetrieveLimits& limits) {
  std::lock_guard<std::mutex> lock(mu_);
  if (!series_error_.ok()) return series_error_;
  if (series_.empty()) {
    return absl::NotFoundError(absl::StrCat(
        node::PeerLabel(peer()), " has no instance of the requested series"));
  }
  node::RetrieveResult result;
  for (const std::string& file : series_) {
    std::error_code ec;
    const int64_t size = static_cast<int64_t>(fs::file_size(file, ec));
    if (ec || result.instances + 1 > limits.max_instances ||
        result.bytes + size > limits.max_bytes) {
      for (const auto& e : fs::directory_iterator(dest_dir, ec)) {
        fs::remove(e.path(), ec);
      }
      return absl::ResourceExhaustedError("over the limits of the pull");
    }
    fs::copy_file(
        file,
        fs::path(dest_dir) / absl::StrCat("pacs-", result.instances, ".dcm"),
        ec);
    ++result.instances;
    result.bytes += size;
  }
  return result;
}

absl::StatusOr<node::StoreResult> FakePeerClient::Store(
    const std::vector<std::string>& files) {
  std::lock_guard<std::mutex> lock(mu_);
  stored_.push_back(files);
  if (!store_answers_.empty()) {
    absl::StatusOr<node::StoreResult> answer =
        std::move(store_answers_.front());
    store_answers_.pop_front();
    return answer;
  }
  node::StoreResult all;
  all.accepted = static_cast<int>(files.size());
  return all;
}

node::PeerSummary FakePeerClient::Summary() const {
  return {.name = peer().name,
          .ae_title = peer().ae_title,
          .address = "(fake)",
          .tls = false};
}

node::PeerClientFactory FakePeerFactory(
    std::function<void(FakePeerClient&)> setup) {
  return [setup = std::move(setup)](
             const node::DicomPeer& peer) -> std::unique_ptr<node::PeerClient> {
    auto client = std::make_unique<FakePeerClient>(peer);
    if (setup) setup(*client);
    return client;
  };
}

FakePeerClient* AsFake(const std::shared_ptr<node::PeerClient>& client) {
  return dynamic_cast<FakePeerClient*>(client.get());
}

}  // namespace interslice::testing
