#include "client/remote/remote_common.h"

#include <chrono>
#include <cstdio>
#include <ctime>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace interslice::client::remote {
namespace {

const char* DeliveryStateName(v1::Delivery::State s) {
  switch (s) {
    case v1::Delivery::PENDING:
      return "pending";
    case v1::Delivery::DELIVERED:
      return "delivered";
    case v1::Delivery::FAILED:
      return "FAILED";
    default:
      return "unknown";
  }
}

}  // namespace

int Fail(const std::string& message) {
  std::fprintf(stderr, "interslice: error: %s\n", message.c_str());
  return 1;
}

void SetTimeout(grpc::ClientContext& context, double seconds) {
  context.set_deadline(
      std::chrono::system_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000)));
}

ProgressEvent ToEvent(const v1::Progress& p) {
  ProgressEvent e;
  e.stage = p.stage();
  e.fraction = p.stage_percent() / 100.0;
  e.iteration = p.iteration();
  e.relative_residual = p.relative_residual();
  e.energy = p.energy();
  return e;
}

const char* StateName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_UPLOADING:
      return "uploading";
    case v1::JOB_STATE_QUEUED:
      return "queued";
    case v1::JOB_STATE_RUNNING:
      return "running";
    case v1::JOB_STATE_SUCCEEDED:
      return "succeeded";
    case v1::JOB_STATE_FAILED:
      return "failed";
    case v1::JOB_STATE_CANCELLED:
      return "cancelled";
    default:
      return "unknown";
  }
}

std::string Printable(std::string text) {
  for (char& c : text) {
    if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = '?';
  }
  return text;
}

std::string UtcTime(int64_t unix_ms) {
  if (unix_ms <= 0) return "-";
  const std::time_t seconds = static_cast<std::time_t>(unix_ms / 1000);
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char text[32];
  std::strftime(text, sizeof(text), "%Y-%m-%d %H:%M:%SZ", &utc);
  return text;
}

std::vector<std::string> DescribeJob(const v1::JobStatus& j) {
  std::vector<std::string> lines;
  const v1::JobOrigin& o = j.source();
  std::string from;
  if (o.door() == v1::JobOrigin::DICOM) {
    from =
        absl::StrCat("DICOM from ", Printable(o.calling_ae()), " to ",
                     Printable(o.called_ae()), ", rule ", Printable(o.rule()));
  } else if (o.door() == v1::JobOrigin::GRPC) {
    from = o.client().empty() ? "client"
                              : absl::StrCat("client ", Printable(o.client()));
    if (!o.pacs_peer().empty()) {
      absl::StrAppend(&from, ", series pulled from peer ",
                      Printable(o.pacs_peer()));
    }
  } else if (!j.origin().empty()) {
    from = Printable(j.origin());  // a record of an older server
  }
  if (!from.empty()) lines.push_back(absl::StrCat("  origin    ", from));
  if (j.instance_count() > 0) {
    lines.push_back(absl::StrFormat(
        "  input     %s, %d instance(s)",
        j.modality().empty() ? "modality unknown" : Printable(j.modality()),
        j.instance_count()));
  }
  if (!j.study_instance_uid().empty() || !j.series_instance_uid().empty()) {
    lines.push_back(
        absl::StrCat("  study     ", Printable(j.study_instance_uid())));
    lines.push_back(
        absl::StrCat("  series    ", Printable(j.series_instance_uid())));
  }
  lines.push_back(absl::StrCat("  times     created ",
                               UtcTime(j.created_unix_ms()), ", started ",
                               UtcTime(j.started_unix_ms()), ", finished ",
                               UtcTime(j.finished_unix_ms())));
  return lines;
}

void PrintDeliveries(const v1::JobStatus& status) {
  for (const v1::Delivery& d : status.deliveries()) {
    std::printf("  to %s: %s, %d of %d instance(s) stored, %d attempt(s)%s%s\n",
                Printable(d.peer()).c_str(), DeliveryStateName(d.state()),
                d.instances_sent(), d.instances_total(), d.attempts(),
                d.last_error().empty() ? "" : "; last error: ",
                Printable(d.last_error()).c_str());
  }
}

}  // namespace interslice::client::remote
