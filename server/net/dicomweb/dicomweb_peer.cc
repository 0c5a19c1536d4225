#include "server/net/dicomweb/dicomweb_peer.h"

#include <utility>

#include "absl/strings/match.h"
#include "server/net/dicomweb/client.h"
#include "server/net/dicomweb/pull.h"

namespace interslice::server::dicomweb {

using node::PeerClient;

DicomWebPeerClient::DicomWebPeerClient(node::DicomPeer peer,
                                       node::PeerClientSettings settings)
    : PeerClient(std::move(peer)), settings_(std::move(settings)) {}

absl::Status DicomWebPeerClient::Echo() {
  return ProbeDicomWebPeer(peer(), settings_.echo_timeout_seconds);
}

std::string DicomWebPeerClient::EchoName() const { return "a QIDO-RS probe"; }

std::string DicomWebPeerClient::EchoAnswered() const {
  return "QIDO-RS answered";
}

absl::StatusOr<node::FindResult> DicomWebPeerClient::Find(
    const node::FindQuery& query, const node::FindLimits& limits) {
  return FindStudiesAndSeriesWeb(peer(), query, limits,
                                 settings_.find_timeout_seconds);
}

absl::StatusOr<node::RetrieveResult> DicomWebPeerClient::Retrieve(
    const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits) {
  return RetrieveSeriesWeb(peer(), study_instance_uid, series_instance_uid,
                           dest_dir, limits,
                           settings_.retrieve_timeout_seconds);
}

absl::StatusOr<node::StoreResult> DicomWebPeerClient::Store(
    const std::vector<std::string>& files) {
  StowClientOptions options;
  options.timeout_seconds = settings_.store_timeout_seconds;
  options.stow_max_instances = settings_.stow_max_instances;
  options.stow_max_bytes = settings_.stow_max_bytes;
  return StowFiles(peer(), files, options);
}

node::PeerSummary DicomWebPeerClient::Summary() const {
  // The URL never holds credentials (the peers file refuses them).
  return {.name = peer().name,
          .ae_title = "(DICOMweb)",
          .address = peer().web.url,
          .tls = absl::StartsWithIgnoreCase(peer().web.url, "https://")};
}

}  // namespace interslice::server::dicomweb
