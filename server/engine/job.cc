#include "server/engine/job.h"

#include <algorithm>

namespace interslice::server {

v1::JobStatus Job::Snapshot(bool with_report) const {
  std::lock_guard<std::mutex> lock(mu_);
  v1::JobStatus status = record_.status();
  if (!with_report) status.clear_report_json();
  return status;
}

void Job::Subscribe(std::shared_ptr<Subscription> subscription) {
  std::lock_guard<std::mutex> lock(mu_);
  subscriptions_.erase(
      std::remove_if(subscriptions_.begin(), subscriptions_.end(),
                     [](const auto& s) { return s->closed(); }),
      subscriptions_.end());
  subscriptions_.push_back(std::move(subscription));
}

void Job::Update(const std::function<void(JobRecord&)>& change) {
  std::vector<std::shared_ptr<Subscription>> subscriptions;
  {
    std::lock_guard<std::mutex> lock(mu_);
    change(record_);
    record_.mutable_status()->set_sequence(record_.status().sequence() + 1);
    subscriptions = subscriptions_;
  }
  for (const auto& s : subscriptions) s->Fire();
}

}  // namespace interslice::server
