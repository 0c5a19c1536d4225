// The status page's rendering with many jobs (issue 27's goal: < 200 ms with
// 1,000 jobs). build/bench/interslice_status_bench
#include <benchmark/benchmark.h>

#include <string>

#include "server/net/http/status_page.h"

namespace interslice::server {
namespace {

StatusSnapshot ManyJobs(int n) {
  StatusSnapshot s;
  s.version = "bench";
  s.now_unix_ms = 1764129600000;
  for (int i = 0; i < n; ++i) {
    v1::JobStatus j;
    j.set_job_id("job-" + std::to_string(i) + ".gezdolrqfyyc4mj2gqzdmnbv");
    j.set_state(i % 10 == 0 ? v1::JOB_STATE_FAILED : v1::JOB_STATE_SUCCEEDED);
    j.set_created_unix_ms(1764129600000 - i * 60000);
    j.set_started_unix_ms(j.created_unix_ms() + 1000);
    j.set_finished_unix_ms(j.created_unix_ms() + 9000);
    j.set_origin("dicom:MODALITY->INTERSLICE rule ct-bone");
    j.mutable_progress()->set_stage("done");
    if (i % 10 == 0) j.set_error_message("the series needs at least 2 slices");
    v1::Delivery* d = j.add_deliveries();
    d->set_peer("orthanc");
    d->set_state(v1::Delivery::DELIVERED);
    d->set_instances_total(291);
    d->set_instances_sent(291);
    s.jobs.push_back(std::move(j));
  }
  s.peers = {
      {.name = "orthanc", .ae_title = "ORTHANC", .address = "pacs:4242"}};
  s.rules = {
      {.name = "ct-bone", .match = "modality CT", .send_to = {"orthanc"}}};
  return s;
}

void BM_RenderStatusHtml(benchmark::State& state) {
  const StatusSnapshot s = ManyJobs(static_cast<int>(state.range(0)));
  size_t bytes = 0;
  for (auto _ : state) {
    std::string html = RenderStatusHtml(s);
    bytes = html.size();
    benchmark::DoNotOptimize(html);
  }
  state.counters["html_bytes"] = static_cast<double>(bytes);
}
BENCHMARK(BM_RenderStatusHtml)
    ->Arg(1000)
    ->Arg(5000)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace interslice::server
