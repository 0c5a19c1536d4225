// Unit tests of the server library's pure parts.
#include <arpa/inet.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "job/options.h"
#include "job/wire.h"
#include "nlohmann/json.hpp"
#include "server/base/audit.h"
#include "server/base/identity.h"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "server/engine/job_worker.h"
#include "server/net/grpc/auth.h"
#include "server/net/grpc/status_map.h"
#include "server/net/grpc/upload_guard.h"
#include "server/net/http/http_handler.h"
#include "server/net/http/status_page.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"

namespace interslice::server {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

std::vector<std::string> ReadLines(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

TEST(AuditLogTest, WritesOneJsonObjectPerLineWithTheAtnaEvent) {
  testing::TempDir dir;
  const std::string path = dir.path() / "audit.jsonl";
  absl::StatusOr<std::unique_ptr<AuditLog>> log =
      AuditLog::Open({.path = path});
  ASSERT_TRUE(log.ok()) << log.status();
  (*log)->Record({.event = "job.fetched",
                  .identity = "alice",
                  .source = "ipv4:127.0.0.1:5000",
                  .job = "0123abcd",
                  .detail = "artifact seg.dcm\nFORGED line"});
  (*log)->Record({.event = "delivery.failed",
                  .outcome = AuditOutcome::kSeriousFailure,
                  .peer = "pacs",
                  .count = 3,
                  .detail = "series 1.2.840.113619.2.55.3.604688119 refused"});
  (*log)->Flush();
  const std::vector<std::string> lines = ReadLines(path);
  ASSERT_EQ(lines.size(), 2u);
  const nlohmann::json first = nlohmann::json::parse(lines[0]);
  EXPECT_EQ(first["event"], "job.fetched");
  EXPECT_EQ(first["atna"], "110106 Export");
  EXPECT_EQ(first["outcome"], "success");
  EXPECT_EQ(first["identity"], "alice");
  EXPECT_EQ(first["job"], "0123abcd");
  EXPECT_FALSE(first.contains("count"));
  // One line stays one line, whatever the detail holds.
  EXPECT_EQ(first["detail"], "artifact seg.dcm\\nFORGED line");
  EXPECT_THAT(first["time"].get<std::string>(),
              ::testing::MatchesRegex("20[0-9-]+T[0-9:]+\\.[0-9]{3}Z"));
  const nlohmann::json second = nlohmann::json::parse(lines[1]);
  EXPECT_EQ(second["atna"], "110104 DICOM Instances Transferred");
  // Every event the server records has its own ATNA mapping (the fallback
  // is for names that are not ours).
  EXPECT_STREQ(AtnaEventFor("kept.listed"), "110112 Query");
  EXPECT_STREQ(AtnaEventFor("kept.rerun"), "110103 DICOM Instances Accessed");
  EXPECT_EQ(second["outcome"], "serious failure");
  EXPECT_EQ(second["count"], 3);
  EXPECT_EQ(second["peer"], "pacs");
  // No UIDs: they identify a patient's study.
  EXPECT_EQ(second["detail"], "series <uid> refused");
}

TEST(AuditLogTest, AppendsAcrossReopensAndRotatesKeepingTheNewestFiles) {
  testing::TempDir dir;
  const std::string path = dir.path() / "audit.jsonl";
  std::ofstream(path) << "{\"earlier\":true}\n";
  {
    absl::StatusOr<std::unique_ptr<AuditLog>> log =
        AuditLog::Open({.path = path, .max_bytes = 4096, .keep = 2});
    ASSERT_TRUE(log.ok()) << log.status();
    for (int i = 0; i < 200; ++i) {
      (*log)->Record({.event = "jobs.listed",
                      .count = i,
                      .detail = std::string(100, 'x')});
    }
  }  // the destructor writes what is queued
  EXPECT_TRUE(std::filesystem::exists(path + ".1"));
  EXPECT_TRUE(std::filesystem::exists(path + ".2"));
  EXPECT_FALSE(std::filesystem::exists(path + ".3"));
  for (const std::string& file : {path, path + ".1", path + ".2"}) {
    EXPECT_LE(std::filesystem::file_size(file), 4096u) << file;
    for (const std::string& line : ReadLines(file)) {
      EXPECT_NO_THROW(nlohmann::json::parse(line)) << line;
    }
  }
  // The newest events are in PATH, the last one last.
  const std::vector<std::string> newest = ReadLines(path);
  ASSERT_FALSE(newest.empty());
  EXPECT_EQ(nlohmann::json::parse(newest.back())["count"], 199);
}

TEST(AuditLogTest, ConcurrentRecordsAreAllWrittenOrCountedAsDropped) {
  testing::TempDir dir;
  const std::string path = dir.path() / "audit.jsonl";
  absl::StatusOr<std::unique_ptr<AuditLog>> log =
      AuditLog::Open({.path = path, .max_queued = 8});
  ASSERT_TRUE(log.ok()) << log.status();
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&log] {
      for (int i = 0; i < 500; ++i) (*log)->Record({.event = "jobs.listed"});
    });
  }
  for (std::thread& t : threads) t.join();
  (*log)->Flush();
  const int64_t dropped = (*log)->dropped_total();
  log->reset();  // writes a pending "audit.dropped" line, if any
  int64_t listed = 0, dropped_noted = 0;
  for (const std::string& line : ReadLines(path)) {
    const nlohmann::json j = nlohmann::json::parse(line);
    if (j["event"] == "jobs.listed") ++listed;
    if (j["event"] == "audit.dropped")
      dropped_noted += j["count"].get<int64_t>();
  }
  EXPECT_EQ(listed + dropped, 2000);
  EXPECT_EQ(dropped_noted, dropped);
}

TEST(AuditLogTest, RefusesBadOptions) {
  testing::TempDir dir;
  EXPECT_FALSE(AuditLog::Open({.path = ""}).ok());
  EXPECT_FALSE(
      AuditLog::Open({.path = dir.path() / "a", .max_bytes = 10}).ok());
  EXPECT_FALSE(AuditLog::Open({.path = dir.path() / "a", .keep = 0}).ok());
  EXPECT_FALSE(AuditLog::Open({.path = dir.path() / "no/such/dir/a"}).ok());
}

StatusSnapshot SnapshotWithTwoJobs() {
  StatusSnapshot s;
  s.version = "9.9";
  s.now_unix_ms = 1764129600000;  // 2025-11-26 04:00:00 UTC
  v1::JobStatus older;
  older.set_job_id("older-job");
  older.set_state(v1::JOB_STATE_FAILED);
  older.set_created_unix_ms(1764129000000);
  older.set_origin("dicom:MODALITY->INTERSLICE rule ct-bone");
  older.set_error_message("the series needs at least 2 slices");
  v1::JobStatus newer;
  newer.set_job_id("newer-job");
  newer.set_state(v1::JOB_STATE_SUCCEEDED);
  newer.set_created_unix_ms(1764129500000);
  newer.set_label("<script>alert(1)</script>");
  v1::Delivery* d = newer.add_deliveries();
  d->set_peer("pacs");
  d->set_state(v1::Delivery::PENDING);
  d->set_instances_total(10);
  d->set_instances_sent(4);
  d->set_last_error("association rejected");
  s.jobs = {older, newer};
  s.peers = {{.name = "pacs", .ae_title = "ORTHANC", .address = "h:4242"}};
  s.rules = {{.name = "ct-bone", .match = "modality CT", .send_to = {"pacs"}}};
  s.spool_used_bytes = int64_t{3} << 30;
  s.spool_quota_bytes = int64_t{20} << 30;
  return s;
}

TEST(StatusPageTest, ShowsJobsNewestFirstWithOriginErrorsAndDeliveries) {
  const std::string html = RenderStatusHtml(SnapshotWithTwoJobs());
  const size_t newer = html.find("newer-job"), older = html.find("older-job");
  ASSERT_NE(newer, std::string::npos);
  ASSERT_NE(older, std::string::npos);
  EXPECT_LT(newer, older);
  EXPECT_THAT(html, HasSubstr("dicom:MODALITY-&gt;INTERSLICE rule ct-bone"));
  EXPECT_THAT(html, HasSubstr("the series needs at least 2 slices"));
  EXPECT_THAT(html, HasSubstr("pacs: pending 4/10"));
  EXPECT_THAT(html, HasSubstr("(association rejected)"));
  EXPECT_THAT(html, HasSubstr("2025-11-26 04:00:00 UTC"));
  EXPECT_THAT(html, HasSubstr("spool 3.0 GiB of 20.0 GiB"));
  EXPECT_THAT(html, HasSubstr("Jobs (2, 1 failed)"));
  // The peer's row counts its pending delivery.
  EXPECT_THAT(html, HasSubstr("<td>h:4242</td><td>1</td><td>0</td><td>0</td>"));
  EXPECT_THAT(html, HasSubstr("<td>ct-bone</td><td>modality CT</td>"));
}

TEST(StatusPageTest, EscapesEverythingAndHasNoScript) {
  const std::string html = RenderStatusHtml(SnapshotWithTwoJobs());
  EXPECT_THAT(html, HasSubstr("&lt;script&gt;alert(1)&lt;/script&gt;"));
  EXPECT_THAT(html, Not(HasSubstr("<script")));
  const nlohmann::json json =
      nlohmann::json::parse(RenderStatusJson(SnapshotWithTwoJobs()));
  ASSERT_EQ(json["jobs"].size(), 2u);
  EXPECT_EQ(json["jobs"][0]["job_id"], "newer-job");
  EXPECT_EQ(json["jobs"][0]["deliveries"][0]["state"], "pending");
  EXPECT_EQ(json["jobs"][1]["state"], "failed");
  EXPECT_EQ(json["peers"][0]["ae_title"], "ORTHANC");
}

// Issue 39, finding 7: series waiting for completion, incomplete or
// dropped were on neither the kept list nor the page.
TEST(StatusPageTest, ShowsSeriesArrivingIncompleteAndDropped) {
  StatusSnapshot s = SnapshotWithTwoJobs();
  s.series.push_back({.state = "receiving",
                      .calling_ae = "MODALITY",
                      .called_ae = "INTERSLICE",
                      .instances = 12,
                      .since_unix_ms = 1764129600000,
                      .why = "being received"});
  s.series.push_back({.state = "incomplete",
                      .calling_ae = "STOW:<b>",
                      .called_ae = "INTERSLICE",
                      .instances = 3,
                      .since_unix_ms = 1764129600000,
                      .why = "incomplete: a STOW-RS request into it did not "
                             "arrive whole"});
  s.series.push_back(
      {.state = "dropped", .calling_ae = "PACS", .instances = 7});
  const std::string html = RenderStatusHtml(s);
  EXPECT_THAT(html, HasSubstr("Series arriving (3, 2 incomplete or dropped)"));
  EXPECT_THAT(html, HasSubstr("<td>incomplete</td><td>STOW:&lt;b&gt;</td>"
                              "<td>INTERSLICE</td><td>3</td>"));
  EXPECT_THAT(html, HasSubstr("did not arrive whole"));
  const nlohmann::json json = nlohmann::json::parse(RenderStatusJson(s));
  ASSERT_EQ(json["series"].size(), 3u);
  EXPECT_EQ(json["series"][1]["state"], "incomplete");
  EXPECT_EQ(json["series"][1]["instances"], 3);
  EXPECT_EQ(json["series"][2]["state"], "dropped");
}

// Regression: a worker whose output does not parse was stopped and reported
// as "the job was cancelled" although nobody cancelled it.
// A route of the HTTP listener (server/net/http/http_handler.h) that
// refuses /hook/nope unauthenticated and echoes what Serve gets.
class EchoHandler : public HttpRequestHandler {
 public:
  std::string_view name() const override { return "echo"; }
  std::optional<HttpServerResponse> Screen(
      std::string_view method, std::string_view path) const override {
    screened.fetch_add(1);
    if (path == "/hook/nope") {
      return HttpServerResponse{.status = 404, .body = "no\n"};
    }
    return std::nullopt;
  }
  HttpServerResponse Serve(const HttpServerRequest& request) const override {
    std::string body;
    char buffer[3];  // small reads: the body streams
    for (int64_t n; (n = request.read(buffer, sizeof(buffer))) > 0;) {
      body.append(buffer, static_cast<size_t>(n));
    }
    return {
        .status = 202,
        .content_type = "text/x-echo",
        .body = absl::StrCat(request.method, " ", request.path, " ",
                             request.identity, " ", request.header("x-test"),
                             " ", request.content_length, " ", body, "\n"),
        .extra_headers = "X-Echo: yes\r\n"};
  }
  mutable std::atomic<int> screened{0};
};

// One HTTP/1.1 exchange over a plain socket: the whole answer (the server
// closes the connection after it).
std::string Exchange(int port, const std::string& request) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  std::string answer;
  if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) ==
          0 &&
      ::send(fd, request.data(), request.size(), MSG_NOSIGNAL) ==
          static_cast<ssize_t>(request.size())) {
    char buffer[4096];
    for (ssize_t n; (n = ::recv(fd, buffer, sizeof(buffer), 0)) > 0;) {
      answer.append(buffer, static_cast<size_t>(n));
    }
  }
  ::close(fd);
  return answer;
}

TEST(StatusServerTest, RoutesAreScreenedAuthenticatedAndServed) {
  testing::TempDir dir;
  const std::string audit_path = dir.path() / "audit.jsonl";
  absl::StatusOr<std::unique_ptr<AuditLog>> audit =
      AuditLog::Open({.path = audit_path});
  ASSERT_TRUE(audit.ok()) << audit.status();
  const Authenticator auth({{.name = "alice", .token = "tok-alice"}}, {});
  EchoHandler echo;
  absl::StatusOr<std::unique_ptr<StatusServer>> server = StatusServer::Start(
      {.listen = "127.0.0.1:0"}, [] { return StatusSnapshot(); }, &auth,
      audit->get(), {{.prefix = "/hook", .handler = &echo}});
  ASSERT_TRUE(server.ok()) << server.status();
  const int port = (*server)->port();
  const std::string kToken = "Authorization: Bearer tok-alice\r\n";

  // Served: method, path, identity, headers and the body in small reads.
  std::string answer =
      Exchange(port, "POST /hook/a HTTP/1.1\r\nHost: x\r\n" + kToken +
                         "X-Test: hi\r\nContent-Length: 5\r\n\r\nhello");
  EXPECT_THAT(answer, ::testing::StartsWith("HTTP/1.1 202 Accepted\r\n"));
  EXPECT_THAT(answer, HasSubstr("Content-Type: text/x-echo\r\n"));
  EXPECT_THAT(answer, HasSubstr("X-Echo: yes\r\n"));
  EXPECT_THAT(answer, HasSubstr("\r\n\r\nPOST /hook/a alice hi 5 hello\n"));
  // The prefix itself is the route's; a HEAD answer has no body.
  answer =
      Exchange(port, "HEAD /hook HTTP/1.1\r\nHost: x\r\n" + kToken + "\r\n");
  EXPECT_THAT(answer, ::testing::StartsWith("HTTP/1.1 202 Accepted\r\n"));
  EXPECT_THAT(answer, ::testing::EndsWith("\r\n\r\n"));
  // Screened before authentication: no token needed to be told 404.
  answer = Exchange(port, "GET /hook/nope HTTP/1.1\r\nHost: x\r\n\r\n");
  EXPECT_THAT(answer, ::testing::StartsWith("HTTP/1.1 404 Not Found\r\n"));
  EXPECT_THAT(answer, ::testing::EndsWith("\r\n\r\nno\n"));
  // No or a wrong token: 401 with a challenge and an audit record; the
  // handler is not served.
  answer = Exchange(port,
                    "POST /hook/a HTTP/1.1\r\nHost: x\r\nAuthorization: "
                    "Bearer wrong\r\nContent-Length: 1\r\n\r\nx");
  EXPECT_THAT(answer, ::testing::StartsWith("HTTP/1.1 401 Unauthorized\r\n"));
  EXPECT_THAT(answer, HasSubstr("WWW-Authenticate: Basic"));
  EXPECT_THAT(answer, Not(HasSubstr("POST /hook/a")));
  // Paths that only start like the prefix are not the route's.
  answer =
      Exchange(port, "GET /hookx HTTP/1.1\r\nHost: x\r\n" + kToken + "\r\n");
  EXPECT_THAT(answer, HasSubstr("the status page is /status"));
  EXPECT_EQ(echo.screened.load(), 4);
  server->reset();
  (*audit)->Flush();
  const std::vector<std::string> lines = ReadLines(audit_path);
  ASSERT_EQ(lines.size(), 1u);
  EXPECT_EQ(nlohmann::json::parse(lines[0])["detail"],
            "echo: missing or wrong token");

  // Routes need a handler and a prefix "/name".
  for (const HttpRoute& bad :
       std::vector<HttpRoute>{{.prefix = "/hook/", .handler = &echo},
                              {.prefix = "hook", .handler = &echo},
                              {.prefix = "/", .handler = &echo},
                              {.prefix = "/hook", .handler = nullptr}}) {
    EXPECT_EQ(StatusServer::Start({.listen = "127.0.0.1:0"},
                                  [] { return StatusSnapshot(); }, &auth,
                                  nullptr, {bad})
                  .status()
                  .code(),
              absl::StatusCode::kInvalidArgument)
        << bad.prefix;
  }
}

TEST(JobWorkerTest, UnreadableWorkerOutputIsAProtocolErrorNotACancellation) {
  testing::TempDir dir;
  const std::filesystem::path worker = dir.path() / "garbling-worker.sh";
  {
    // A frame header announcing 4 GiB, more than any frame may hold; then
    // the worker stays alive until it is killed.
    std::ofstream out(worker);
    out << "#!/bin/sh\nprintf '\\377\\377\\377\\377'\nexec sleep 60\n";
  }
  std::filesystem::permissions(worker, std::filesystem::perms::owner_all);
  WorkerOptions options;
  options.executable = worker.string();
  WorkerOutcome outcome;
  const absl::StatusOr<job::JobResult> result = RunInWorkerProcess(
      spool::v1::WorkerRequest(), ComputeContext(), options, &outcome);
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInternal)
      << result.status();
  EXPECT_THAT(result.status().message(), HasSubstr("protocol error"));
  EXPECT_THAT(result.status().message(), Not(HasSubstr("cancelled")));
  EXPECT_FALSE(outcome.crashed);
}

// This process's resident set size now, bytes (VmRSS).
int64_t ResidentBytes() {
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    long long kilobytes = 0;
    if (std::sscanf(line.c_str(), "VmRSS: %lld kB", &kilobytes) == 1) {
      return kilobytes * 1024;
    }
  }
  return -1;
}

// Issue 42: peak_rss_bytes counted the parent's memory. posix_spawn shares
// the server's memory until the worker's execve, and Linux carries that
// image's peak into the worker's ru_maxrss (wait4's and its own getrusage):
// a worker reported the server's peak. The same tiny job in a worker, once
// as this process is and once after it touched 320 MB more, must report
// the same peak: the worker's own, in the result and in the job's report.
TEST(JobWorkerTest, ReportPeakRssIsTheWorkersOwnNotTheServers) {
  testing::TempDir dir;
  job::InterpolationOptions options;
  options.inputs = {"unused: the worker reads input_dir"};
  options.out = "unused: the worker writes output_dir";
  options.threshold = 300;
  options.roi = "200,40,0,296,136,4";
  options.method = "linear";
  options.factor = 2;
  options.volume = "none";
  options.previews = "none";
  const absl::StatusOr<JobSpec> spec = job::BuildJobSpec(options);
  ASSERT_TRUE(spec.ok()) << spec.status();
  WorkerOptions worker;
  worker.executable = ::interslice::testing::ServerPath();
  auto peaks_of = [&](const std::string& name) -> std::pair<int64_t, int64_t> {
    spool::v1::WorkerRequest request;
    *request.mutable_spec() = job::ToWire(*spec);
    request.set_input_dir(std::string(::interslice::testing::TestDataDir()) +
                          "/ct-thick");
    request.set_output_dir((dir.path() / name).string());
    std::filesystem::create_directories(dir.path() / name);
    const absl::StatusOr<job::JobResult> result =
        RunInWorkerProcess(request, ComputeContext(), worker, nullptr);
    EXPECT_TRUE(result.ok()) << result.status();
    if (!result.ok()) return {-1, -1};
    return {result->peak_rss_bytes,
            nlohmann::json::parse(result->report_json)["peak_rss_bytes"]
                .get<int64_t>()};
  };
  const auto [alone, alone_report] = peaks_of("alone");

  constexpr size_t kServerBytes = size_t{320} << 20;
  std::vector<char> ballast(kServerBytes);
  std::memset(ballast.data(), 1, ballast.size());  // every page resident
  ASSERT_GE(ResidentBytes(), static_cast<int64_t>(kServerBytes));
  const auto [beside, beside_report] = peaks_of("beside-ballast");
  EXPECT_EQ(ballast[kServerBytes - 1], 1);

  EXPECT_GT(alone, 0);
  EXPECT_EQ(alone_report, alone);
  EXPECT_EQ(beside_report, beside);
  EXPECT_LT(beside, alone + static_cast<int64_t>(kServerBytes / 2))
      << "alone " << alone << " bytes, beside a server of " << ResidentBytes()
      << " bytes: " << beside;
}

TEST(RedactPhiTest, ReplacesUidsButKeepsNumbers) {
  EXPECT_EQ(RedactPhi("several series: 1.2.840.113619.2.55.3 (CT, 4 images)."),
            "several series: <uid> (CT, 4 images).");
  EXPECT_EQ(RedactPhi("file 3 of 12 bytes, spacing 0.45 mm, v1.2.3"),
            "file 3 of 12 bytes, spacing 0.45 mm, v1.2.3");
}

TEST(LogSafeTest, EscapesControlCharactersAndInvalidUtf8) {
  EXPECT_EQ(LogSafe("plain text, 1.5 mm"), "plain text, 1.5 mm");
  EXPECT_EQ(LogSafe("a\nFORGED b\r\tc"), "a\\nFORGED b\\r\\tc");
  EXPECT_EQ(LogSafe(std::string("x\0y\x1b[31m\x7f", 9)),
            "x\\x00y\\x1b[31m\\x7f");
  // Valid UTF-8 stays; stray, overlong, surrogate and truncated bytes not.
  EXPECT_EQ(LogSafe("Gr\xc3\xb6\xc3\x9f\xe2\x82\xac \xf0\x9f\x98\x80"),
            "Gr\xc3\xb6\xc3\x9f\xe2\x82\xac \xf0\x9f\x98\x80");
  EXPECT_EQ(LogSafe("\xff\xc0\xaf\xed\xa0\x80\xe2\x82"),
            "\\xff\\xc0\\xaf\\xed\\xa0\\x80\\xe2\\x82");
  // Idempotent, so that layers may each apply it.
  const std::string once = LogSafe("a\n\\n\xff");
  EXPECT_EQ(LogSafe(once), once);
  EXPECT_TRUE(IsLogSafe(once));
  EXPECT_FALSE(IsLogSafe("a\nb"));
  EXPECT_FALSE(IsLogSafe("\xc3"));
  EXPECT_TRUE(IsLogSafe("\xc3\xb6"));
}

TEST(RedactPhiTest, OutputIsOneLine) {
  EXPECT_EQ(RedactPhi("volume \"\nFORGED 1.2.840.10008.1\" is not in"),
            "volume \"\\nFORGED <uid>\" is not in");
}

TEST(StatusMapTest, CodesMapOneToOne) {
  EXPECT_EQ(ToGrpcStatus(absl::ResourceExhaustedError("x")).error_code(),
            grpc::RESOURCE_EXHAUSTED);
  EXPECT_EQ(ToGrpcStatus(absl::DeadlineExceededError("x")).error_code(),
            grpc::DEADLINE_EXCEEDED);
  EXPECT_TRUE(ToGrpcStatus(absl::OkStatus()).ok());
}

// Issue 22: a job whose output hit a full spool failed INTERNAL with the
// server's spool path in the client's message.
TEST(StatusMapTest, FullDiskIsResourceExhaustedWithoutPaths) {
  const absl::Status write = absl::InternalError(
      "cannot write /var/tmp/spool/jobs/j1/out/volume.nii.gz: No space left "
      "on device");
  const absl::Status mapped = DiskFullAsResourceExhausted(write, false);
  EXPECT_EQ(mapped.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(std::string(mapped.message()),
              ::testing::StartsWith("disk full"));
  EXPECT_THAT(std::string(mapped.message()),
              ::testing::Not(::testing::HasSubstr("/var/tmp")));
  // A write error the writer did not explain, on a spool with no room.
  EXPECT_EQ(DiskFullAsResourceExhausted(
                absl::InternalError("Could not write file"), true)
                .code(),
            absl::StatusCode::kResourceExhausted);
  // Otherwise nothing changes.
  EXPECT_EQ(DiskFullAsResourceExhausted(
                absl::InternalError("Could not write file"), false),
            absl::InternalError("Could not write file"));
  EXPECT_EQ(
      DiskFullAsResourceExhausted(absl::InvalidArgumentError("bad"), true),
      absl::InvalidArgumentError("bad"));
  EXPECT_EQ(DiskFullAsResourceExhausted(absl::CancelledError("stop"), true),
            absl::CancelledError("stop"));
}

TEST(TokenFileTest, OneTokenAloneIsTheDefaultIdentity) {
  auto tokens = ParseTokenFile("  s3cret-token\n");
  ASSERT_TRUE(tokens.ok()) << tokens.status();
  ASSERT_EQ(tokens->size(), 1u);
  EXPECT_EQ((*tokens)[0].name, "default");
  EXPECT_EQ((*tokens)[0].token, "s3cret-token");
}

TEST(TokenFileTest, NamedTokens) {
  auto tokens =
      ParseTokenFile("# who:token\nalice: tok-a\n\nbob:tok:b\nops@site:c\n");
  ASSERT_TRUE(tokens.ok()) << tokens.status();
  ASSERT_EQ(tokens->size(), 3u);
  EXPECT_EQ((*tokens)[0].name, "alice");
  EXPECT_EQ((*tokens)[0].token, "tok-a");
  EXPECT_EQ((*tokens)[1].token, "tok:b");  // split at the first ':'
  EXPECT_EQ((*tokens)[2].name, "ops@site");
  for (const char* bad :
       {"", "# only a comment\n", "alice:a\nbob\n", "alice:a\nalice:b\n",
        "alice:a\nbob:a\n", "al ice:a\n", ":a\n", "alice:\n", "alice:a b\n",
        "two words\n"}) {
    auto parsed = ParseTokenFile(bad);
    EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument)
        << bad;
    // A refusal never quotes a token.
    if (!parsed.ok()) {
      EXPECT_EQ(parsed.status().message().find("a b"), std::string::npos);
    }
  }
}

TEST(AuthenticatorTest, MatchesBearerTokensByName) {
  Authenticator auth({{"alice", "tok-a"}, {"bob", "tok-b"}}, {"bob"});
  EXPECT_EQ(auth.MatchBearer("Bearer tok-a"), "alice");
  EXPECT_EQ(auth.MatchBearer("Bearer tok-b"), "bob");
  EXPECT_EQ(auth.MatchBearer("Bearer tok-"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer("Bearer tok-ab"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer("tok-a"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer(""), std::nullopt);
  EXPECT_TRUE(Authenticator::MayAccess({"alice", false}, "alice"));
  EXPECT_FALSE(Authenticator::MayAccess({"bob", false}, "alice"));
  EXPECT_TRUE(Authenticator::MayAccess({"bob", true}, "alice"));
  EXPECT_TRUE(Authenticator::MayAccess({"", false}, ""));
  // Without authentication the one anonymous user also sees the jobs the
  // DICOM listener made (regression: they were invisible to every client).
  EXPECT_TRUE(Authenticator::MayAccess({"", false}, "dicom"));
  EXPECT_FALSE(Authenticator::MayAccess({"alice", false}, "dicom"));
}

TEST(PeerAddressTest, DropsThePort) {
  EXPECT_EQ(PeerAddress("ipv4:10.1.2.3:5000"), "10.1.2.3");
  EXPECT_EQ(PeerAddress("ipv6:[::1]:5000"), "::1");
  EXPECT_EQ(PeerAddress("ipv6:%5B::1%5D:5000"), "::1");
  EXPECT_EQ(PeerAddress("unix:/tmp/socket"), "unix:/tmp/socket");
}

TEST(UploadGuardTest, LimitsUploadsInAllAndPerPeer) {
  UploadGuardOptions options;
  options.max_concurrent = 3;
  options.max_per_peer = 2;
  options.idle_timeout_seconds = 0;
  UploadGuard guard(options);
  auto a1 = guard.Begin("a", nullptr);
  auto a2 = guard.Begin("a", nullptr);
  ASSERT_TRUE(a1.ok() && a2.ok());
  auto a3 = guard.Begin("a", nullptr);
  EXPECT_EQ(a3.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(a3.status().message().find("--max-uploads-per-peer"),
            std::string::npos);
  auto b1 = guard.Begin("b", nullptr);
  ASSERT_TRUE(b1.ok());
  auto c1 = guard.Begin("c", nullptr);
  EXPECT_EQ(c1.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(c1.status().message().find("--max-concurrent-uploads"),
            std::string::npos);
  EXPECT_EQ(guard.active(), 3);
  (*a1)->Release();
  (*a1)->Release();  // idempotent
  EXPECT_EQ(guard.active(), 2);
  EXPECT_TRUE(guard.Begin("a", nullptr).ok());  // released with the ticket
  EXPECT_EQ(guard.active(), 2);
  b1->reset();  // a ticket dropped without Release frees its slot too
  EXPECT_EQ(guard.active(), 1);
}

TEST(UploadGuardTest, ReportsStallsUntilClosed) {
  UploadGuardOptions options;
  // Five times the pause between progress calls below, so that a loaded
  // machine stretching one pause does not look like a stall.
  options.idle_timeout_seconds = 0.5;
  UploadGuard guard(options);
  std::atomic<int> stalls{0};
  absl::Status last;
  std::mutex mu;
  auto ticket = guard.Begin("a", [&](const absl::Status& s, bool idle) {
    std::lock_guard<std::mutex> lock(mu);
    EXPECT_TRUE(idle);
    last = s;
    ++stalls;
  });
  ASSERT_TRUE(ticket.ok());
  // Progress keeps it alive.
  for (int i = 0; i < 8; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    (*ticket)->Progress();
  }
  EXPECT_EQ(stalls, 0);
  EXPECT_TRUE(::interslice::testing::WaitFor([&] { return stalls >= 1; },
                                             std::chrono::seconds(30)));
  {
    std::lock_guard<std::mutex> lock(mu);
    EXPECT_EQ(last.code(), absl::StatusCode::kDeadlineExceeded);
    EXPECT_EQ(last.message(),
              "upload stalled: no data for 0.5 s; the server cancelled it");
  }
  (*ticket)->Close();
  const int seen = stalls;
  // A check that nothing happens: no report after Close, for longer than
  // the idle timeout (a sleep, not a wait).
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));
  EXPECT_EQ(stalls, seen);
}

TEST(UploadGuardTest, ReportsTheTotalLimitOnce) {
  UploadGuardOptions options;
  options.idle_timeout_seconds = 0;
  options.total_timeout_seconds = 0.2;
  UploadGuard guard(options);
  std::atomic<int> calls{0};
  auto ticket = guard.Begin("a", [&](const absl::Status& s, bool idle) {
    EXPECT_FALSE(idle);
    EXPECT_EQ(s.code(), absl::StatusCode::kDeadlineExceeded);
    ++calls;
  });
  ASSERT_TRUE(ticket.ok());
  // Data keeps arriving, yet the total limit applies...
  EXPECT_TRUE(::interslice::testing::WaitFor(
      [&] {
        (*ticket)->Progress();
        return calls >= 1;
      },
      std::chrono::seconds(30), std::chrono::milliseconds(100)));
  // ...once: no second report while data keeps coming (a check that
  // nothing happens, for 0.8 s).
  for (int i = 0; i < 8; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    (*ticket)->Progress();
  }
  EXPECT_EQ(calls, 1);
  (*ticket)->Close();
}

}  // namespace
}  // namespace interslice::server
