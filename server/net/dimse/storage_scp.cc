#include "server/net/dimse/storage_scp.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "server/net/dimse/association.h"
#include "server/net/dimse/connection_gate.h"
#include "server/node/received_instance.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dimse {

using node::PeersConfig;

struct StorageScp::Impl {
  StorageScpOptions options;
  std::unique_ptr<RefusalLog> refusals;
  std::unique_ptr<ConnectionGate> gate;
  std::unique_ptr<AssociationRunner> runner;
  std::vector<std::thread> workers;
  std::mutex mu;
  std::condition_variable cv;
  std::deque<ReadyConnection> queue;
  int idle = 0;  // workers waiting for a connection (not counting queued)
  std::map<std::string, int> per_source;  // queued or running
  int per_source_limit = 1;
  bool stopping = false;
  bool stopped = false;

  // On the gate's thread: never blocks.
  Handoff Take(ReadyConnection& c) {
    std::lock_guard<std::mutex> lock(mu);
    if (stopping) return Handoff::kBusy;
    if (idle <= static_cast<int>(queue.size())) return Handoff::kBusy;
    int& mine = per_source[c.source];
    if (mine >= per_source_limit) {
      if (mine == 0) per_source.erase(c.source);
      return Handoff::kSourceBusy;
    }
    ++mine;
    // Freed once, at the association's end or when its worker is done,
    // whichever comes first (issue 39: a sender at its limit that
    // associated again at once was refused while the worker cleaned up).
    auto freed = std::make_shared<std::atomic<bool>>(false);
    c.release_slot = [this, source = c.source, freed] {
      if (freed->exchange(true)) return;
      std::lock_guard<std::mutex> slot_lock(mu);
      if (--per_source[source] <= 0) per_source.erase(source);
    };
    queue.push_back(std::move(c));
    cv.notify_one();
    return Handoff::kTaken;
  }

  void Work() {
    std::unique_lock<std::mutex> lock(mu);
    while (true) {
      ++idle;
      cv.wait(lock, [this] { return stopping || !queue.empty(); });
      --idle;
      if (queue.empty()) return;  // stopping, nothing left
      ReadyConnection c = std::move(queue.front());
      queue.pop_front();
      const std::function<void()> release_slot = c.release_slot;
      lock.unlock();
      runner->Serve(std::move(c));
      release_slot();
      lock.lock();
    }
  }
};

absl::StatusOr<std::unique_ptr<StorageScp>> StorageScp::Start(
    const StorageScpOptions& options, node::Intake* intake, Metrics* metrics) {
  if (options.ae_titles.empty()) {
    return absl::InvalidArgumentError("the DICOM listener needs an AE title");
  }
  if (options.max_associations < 1 || options.max_associations > 1000) {
    return absl::InvalidArgumentError(
        "--dicom-max-associations must be between 1 and 1000");
  }
  // PS3.8: 0 means unlimited, which we never offer; DCMTK's floor is 4096.
  if (options.max_pdu_bytes < 4096 || options.max_pdu_bytes > 131072) {
    return absl::InvalidArgumentError(
        "--dicom-max-pdu must be between 4096 and 131072 bytes");
  }
  if (options.max_pending < 1 || options.max_pending_per_source < 1 ||
      options.max_associations_per_source < 0) {
    return absl::InvalidArgumentError(
        "--dicom-max-pending and --dicom-max-pending-per-source must be >= 1");
  }
  if (!(options.acse_timeout_seconds > 0) ||
      !(options.pdu_timeout_seconds > 0) ||
      !(options.dimse_timeout_seconds > 0)) {
    return absl::InvalidArgumentError(
        "--dicom-acse-timeout, --dicom-pdu-timeout and --dicom-dimse-timeout "
        "must be > 0");
  }
  std::unique_ptr<StorageScp> scp(new StorageScp());
  scp->impl_ = std::make_unique<Impl>();
  Impl& impl = *scp->impl_;
  impl.options = options;
  impl.per_source_limit = options.max_associations_per_source > 0
                              ? options.max_associations_per_source
                              : std::max(1, (options.max_associations + 1) / 2);
  impl.refusals = std::make_unique<RefusalLog>(metrics, options.audit);

  GateOptions gate;
  gate.host = options.host;
  gate.port = options.port;
  gate.request_timeout_seconds = options.acse_timeout_seconds;
  gate.max_pending = options.max_pending;
  gate.max_pending_per_source = options.max_pending_per_source;
  gate.tls = !options.tls.certificate.empty();
  gate.send_timeout_seconds = options.dimse_timeout_seconds;
  gate.guard.max_pdata_bytes = options.max_pdu_bytes + 64;
  absl::StatusOr<std::unique_ptr<ConnectionGate>> bound =
      ConnectionGate::Bind(gate, impl.refusals.get());
  if (!bound.ok()) return bound.status();
  impl.gate = *std::move(bound);
  absl::StatusOr<std::unique_ptr<AssociationRunner>> runner =
      AssociationRunner::Create(options, intake, metrics, impl.refusals.get(),
                                impl.gate.get());
  if (!runner.ok()) return runner.status();
  impl.runner = *std::move(runner);
  for (int i = 0; i < options.max_associations; ++i) {
    impl.workers.emplace_back([&impl] { impl.Work(); });
  }
  {
    // Every worker waits before the first connection is handed over.
    std::unique_lock<std::mutex> lock(impl.mu);
    while (impl.idle < options.max_associations) {
      lock.unlock();
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
      lock.lock();
    }
  }
  Impl* raw = &impl;
  impl.gate->Start([raw](ReadyConnection& c) { return raw->Take(c); });
  std::string titles;
  for (const std::string& ae : options.ae_titles) {
    absl::StrAppend(&titles, titles.empty() ? "" : ", ", ae);
  }
  spdlog::info(
      "dicom: listening on {} port {} as {}{} ({} peer(s), at most {} "
      "association(s), {} from one address)",
      LogSafe(impl.gate->address()), impl.gate->port(), LogSafe(titles),
      gate.tls ? " with TLS" : "", options.peers.peers.size(),
      options.max_associations, impl.per_source_limit);
  return scp;
}

void StorageScp::SetPeers(PeersConfig peers) {
  if (impl_) impl_->runner->SetPeers(std::move(peers));
}

int StorageScp::port() const { return impl_ ? impl_->gate->port() : 0; }

StorageScp::~StorageScp() { Stop(); }

void StorageScp::Stop() {
  // Start() may have failed half-way (the address taken): nothing runs.
  if (!impl_ || !impl_->gate) return;
  {
    std::lock_guard<std::mutex> lock(impl_->mu);
    if (impl_->stopped) return;
    impl_->stopped = true;
  }
  // No new connections; those in an association end by themselves (their
  // deadlines still run: the gate watches them until it stops).
  impl_->gate->StopAccepting();
  {
    std::lock_guard<std::mutex> lock(impl_->mu);
    impl_->stopping = true;
  }
  impl_->cv.notify_all();
  for (std::thread& t : impl_->workers) t.join();
  impl_->workers.clear();
  impl_->gate->Stop();
  spdlog::info("dicom: listener stopped");
}

}  // namespace interslice::server::dimse
