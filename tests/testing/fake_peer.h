// A DICOM peer in the test's process (server/node/peer.h, PeerClient): it
// answers what the test tells it to and records what it was sent, so that
// the node's outbox, registry and pulls are tested without a PACS.
// Thread-safe.
#ifndef INTERSLICE_TESTS_TESTING_FAKE_PEER_H_
#define INTERSLICE_TESTS_TESTING_FAKE_PEER_H_

#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/peer.h"

namespace interslice::testing {

class FakePeerClient : public server::node::PeerClient {
 public:
  explicit FakePeerClient(server::node::DicomPeer peer)
      : PeerClient(std::move(peer)) {}

  // Store answers these, one per call, then accepts every file.
  void QueueStoreAnswer(absl::StatusOr<server::node::StoreResult> answer);
  // Echo answers this (OK by default).
  void SetEcho(absl::Status status);
  // Retrieve copies these files into the destination folder, or fails
  // with `error` when it is set.
  void SetSeries(std::vector<std::string> files, absl::Status error = {});
  void SetFind(absl::StatusOr<server::node::FindResult> result);

  // What Store was given, call by call.
  std::vector<std::vector<std::string>> stored() const;

  absl::Status Echo() override;
  std::string EchoName() const override { return "a fake echo"; }
  std::string EchoAnswered() const override { return "fake echo answered"; }
  absl::StatusOr<server::node::FindResult> Find(
      const server::node::FindQuery& query,
      const server::node::FindLimits& limits) override;
  absl::StatusOr<server::node::RetrieveResult> Retrieve(
      const std::string& study_instance_uid,
      const std::string& series_instance_uid, const std::string& dest_dir,
      const server::node::RetrieveLimits& limits) override;
  absl::StatusOr<server::node::StoreResult> Store(
      const std::vector<std::string>& files) override;
  server::node::PeerSummary Summary() const override;

 private:
  mutable std::mutex mu_;
  std::deque<absl::StatusOr<server::node::StoreResult>> store_answers_;
  std::vector<std::vector<std::string>> stored_;
  absl::Status echo_;
  std::vector<std::string> series_;
  absl::Status series_error_;
  absl::StatusOr<server::node::FindResult> find_ = server::node::FindResult{};
};

// A registry factory (node::PeerRegistry) that makes FakePeerClients,
// each set up by `setup` (may be empty) as it is made. The registry's
// clients are then FakePeerClients: AsFake reaches one.
server::node::PeerClientFactory FakePeerFactory(
    std::function<void(FakePeerClient&)> setup = {});
FakePeerClient* AsFake(const std::shared_ptr<server::node::PeerClient>& client);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_FAKE_PEER_H_
