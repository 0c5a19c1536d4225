#include "server/node/peer_registry.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace interslice::server::node {

PeerRegistry::PeerRegistry(PeerClientFactory factory, PeersConfig peers)
    : factory_(std::move(factory)) {
  SetPeers(std::move(peers));
}

void PeerRegistry::SetPeers(PeersConfig peers) {
  auto next = std::make_shared<Generation>();
  for (const DicomPeer& peer : peers.peers) {
    next->clients.push_back(factory_(peer));
  }
  next->config = std::make_shared<const PeersConfig>(std::move(peers));
  std::lock_guard<std::mutex> lock(mu_);
  generation_ = std::move(next);
}

std::shared_ptr<const PeerRegistry::Generation> PeerRegistry::generation()
    const {
  std::lock_guard<std::mutex> lock(mu_);
  return generation_;
}

std::shared_ptr<const PeersConfig> PeerRegistry::config() const {
  return generation()->config;
}

std::shared_ptr<PeerClient> PeerRegistry::Find(const std::string& name) const {
  for (const std::shared_ptr<PeerClient>& client : generation()->clients) {
    if (client->name() == name) return client;
  }
  return nullptr;
}

std::vector<std::shared_ptr<PeerClient>> PeerRegistry::clients() const {
  return generation()->clients;
}

bool PeerRegistry::empty() const { return generation()->clients.empty(); }

absl::Status PeerRegistry::CheckPeers(
    const std::vector<std::string>& names) const {
  const std::shared_ptr<const Generation> now = generation();
  for (const std::string& name : names) {
    bool known = false;
    for (const auto& client : now->clients) known |= client->name() == name;
    if (!known) {
      std::vector<std::string> configured;
      for (const auto& client : now->clients) {
        configured.push_back(client->name());
      }
      return absl::InvalidArgumentError(absl::StrCat(
          "send_to names an unknown DICOM peer \"", name, "\" (configured: ",
          configured.empty() ? "none; see --dicom-peers"
                             : absl::StrJoin(configured, ", "),
          ")"));
    }
  }
  return absl::OkStatus();
}

absl::Status PeerRegistry::CheckPeer(const std::string& name) const {
  if (Find(name) != nullptr) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("spec.pacs_source.peer: unknown DICOM peer \"", name, "\""));
}

absl::StatusOr<RetrievedSeries> PeerRegistry::Retrieve(
    const v1::PacsSeriesSource& source, const std::string& dest_dir,
    int64_t max_bytes, const CancellationToken* cancel) {
  std::shared_ptr<PeerClient> client = Find(source.peer());
  if (client == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat("DICOM peer ", source.peer(), " is no longer configured"));
  }
  RetrieveLimits limits;
  limits.max_bytes = max_bytes;
  limits.cancel = cancel;
  absl::StatusOr<RetrieveResult> result =
      client->Retrieve(source.study_instance_uid(),
                       source.series_instance_uid(), dest_dir, limits);
  if (!result.ok()) return result.status();
  return RetrievedSeries{result->instances, result->bytes};
}

}  // namespace interslice::server::node
