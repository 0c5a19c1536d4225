#include "server/net/dimse/dimse_peer.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "server/net/dimse/echo.h"
#include "server/net/dimse/find.h"
#include "server/net/dimse/retrieve.h"
#include "server/net/dimse/store.h"

namespace interslice::server::dimse {

using node::PeerClient;

DimsePeerClient::DimsePeerClient(node::DicomPeer peer,
                                 node::PeerClientSettings settings,
                                 MoveDestination move_destination)
    : PeerClient(std::move(peer)),
      settings_(std::move(settings)),
      move_destination_(std::move(move_destination)) {}

absl::Status DimsePeerClient::Echo() {
  return EchoPeer(peer(), settings_.calling_ae_title, settings_.tls,
                  settings_.echo_timeout_seconds);
}

std::string DimsePeerClient::EchoName() const { return "a C-ECHO"; }

std::string DimsePeerClient::EchoAnswered() const {
  return absl::StrCat("C-ECHO answered (calling as ",
                      settings_.calling_ae_title, ")");
}

absl::StatusOr<node::FindResult> DimsePeerClient::Find(
    const node::FindQuery& query, const node::FindLimits& limits) {
  FindOptions options;
  options.calling_ae_title = settings_.calling_ae_title;
  options.tls = settings_.tls;
  options.timeout_seconds = settings_.find_timeout_seconds;
  options.max_pdu_bytes = settings_.max_pdu_bytes;
  options.max_studies = limits.max_studies;
  options.max_series = limits.max_series;
  return FindStudiesAndSeries(peer(), query, options);
}

absl::StatusOr<node::RetrieveResult> DimsePeerClient::Retrieve(
    const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits) {
  RetrieveOptions options;
  options.calling_ae_title = settings_.calling_ae_title;
  options.tls = settings_.tls;
  options.timeout_seconds = settings_.retrieve_timeout_seconds;
  options.max_pdu_bytes = settings_.max_pdu_bytes;
  options.move_destination_ae = move_destination_.ae_title;
  options.pending_moves = move_destination_.pending_moves;
  return RetrieveSeries(peer(), study_instance_uid, series_instance_uid,
                        dest_dir, limits, options);
}

absl::StatusOr<node::StoreResult> DimsePeerClient::Store(
    const std::vector<std::string>& files) {
  StoreOptions options;
  options.calling_ae_title = settings_.calling_ae_title;
  options.tls = settings_.tls;
  options.timeout_seconds = settings_.store_timeout_seconds;
  options.max_pdu_bytes = settings_.max_pdu_bytes;
  return StoreFiles(peer(), files, options);
}

node::PeerSummary DimsePeerClient::Summary() const {
  return {.name = peer().name,
          .ae_title = peer().ae_title,
          .address = absl::StrCat(peer().host, ":", peer().port),
          .tls = peer().tls};
}

}  // namespace interslice::server::dimse
