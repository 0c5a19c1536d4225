// STOW-RS end to end: a real interslice-server process (DICOM node and HTTP
// listener on loopback), the phantom POSTed by the curl command, bad
// requests from curl and from a raw socket (slow loris, a 10 GB
// Content-Length).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "server/net/http/status_page.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";
const std::string kSmallSeries =
    std::string(::interslice::testing::SourceDir()) + "/tests/data/ct-tilt";
const char kType[] =
    "Content-Type: multipart/related; type=\"application/dicom\"; "
    "boundary=stow-test-boundary";

std::vector<std::string> DicomFiles(const std::string& dir) {
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  return files;
}

// A STOW-RS body of `files` written to `path` (without its close delimiter
// when `close` is false).
void WriteBody(const std::string& path, const std::vector<std::string>& files,
               bool close = true) {
  std::ofstream out(path, std::ios::binary);
  for (const std::string& f : files) {
    out << "--stow-test-boundary\r\nContent-Type: application/dicom\r\n\r\n"
        << std::ifstream(f, std::ios::binary).rdbuf() << "\r\n";
  }
  if (close) out << "--stow-test-boundary--\r\n";
}

// curl's body and HTTP status code.
std::pair<int, std::string> Curl(const std::vector<std::string>& args) {
  const CommandResult r =
      RunCommand(Cat({"/usr/bin/curl", "-s", "-S", "--max-time", "60", "-w",
                      "\n%{http_code}"},
                     args),
                 90);
  const size_t newline = r.out.rfind('\n');
  if (newline == std::string::npos) return {0, r.out + r.err};
  return {std::atoi(r.out.c_str() + newline + 1), r.out.substr(0, newline)};
}

int Connect(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

// Whether the server closed `fd` (what it sent before is appended to
// `answer`); waits up to `ms`.
bool ClosedByServer(int fd, int ms, std::string* answer) {
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
  char buffer[4096];
  while (true) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    pollfd p{fd, POLLIN, 0};
    if (left.count() <= 0 ||
        ::poll(&p, 1, static_cast<int>(left.count())) <= 0) {
      return false;
    }
    const ssize_t n = ::recv(fd, buffer, sizeof(buffer), MSG_DONTWAIT);
    if (n > 0) {
      answer->append(buffer, static_cast<size_t>(n));
    } else if (n == 0 || (errno != EAGAIN && errno != EWOULDBLOCK)) {
      return true;
    }
  }
}

class StowServerTest : public ::testing::Test {
 protected:
  // One job per request (complete_on_request), never by the stable wait.
  virtual std::string Rules() const {
    return "stable_seconds: 600\n"
           "rules:\n"
           "  - name: stow-ct\n"
           "    match: {modality: CT, called_ae: INTERSLICE, calling_ae: "
           "\"STOW:alice\"}\n"
           "    job: {threshold: 300, roi: [208, 208, 0, 304, 304, 28]}\n"
           "    complete_on_request: true\n";
  }

  void SetUp() override {
    std::ofstream(dir_ / "tokens") << "alice:tok-alice\nops:tok-ops\n";
    std::ofstream(dir_ / "rules.yaml") << Rules();
    http_port_ = FreeTcpPort();
    base_ = absl::StrCat("http://127.0.0.1:", http_port_);
    server_ = std::make_unique<ServerProcess>(ServerOptions{
        .spool = dir_ / "spool",
        .log = dir_ / "server.log",
        .extra = {"--auth-token-file", dir_ / "tokens", "--admin-identity",
                  "ops", "--dicom-listen", "127.0.0.1:0", "--rules",
                  dir_ / "rules.yaml", "--http-listen",
                  absl::StrCat("127.0.0.1:", http_port_),
                  "--http-request-timeout", "2", "--stow-max-body-bytes",
                  "16000000", "--audit-log", dir_ / "audit.jsonl",
                  "--metrics-listen", "127.0.0.1:0"}});
    ASSERT_TRUE(server_->Start());
  }

  std::pair<int, std::string> Post(const std::string& body_file,
                                   const std::string& path = "",
                                   std::vector<std::string> more = {}) {
    return Curl(Cat(Cat({"-u", "x:tok-alice", "-H", kType, "--data-binary",
                         "@" + body_file},
                        more),
                    {base_ + "/dicomweb/studies" + path}));
  }

  nlohmann::json Status() {
    auto [code, body] = Curl({"-u", "x:tok-ops", base_ + "/status.json"});
    EXPECT_EQ(code, 200) << body;
    return code == 200 ? nlohmann::json::parse(body) : nlohmann::json();
  }

  TempDir dir_;
  int http_port_ = 0;
  std::string base_;
  std::unique_ptr<ServerProcess> server_;
};

TEST_F(StowServerTest, SeriesPostedMakesTheRulesJobAndBadRequestsAreRefused) {
  // A malformed body (no close delimiter) of a small series: 400, and the
  // instances that arrived are not made into a job.
  WriteBody(dir_ / "cut.body", DicomFiles(kSmallSeries), /*close=*/false);
  ASSERT_EQ(DicomFiles(kSmallSeries).size(), 3u);
  auto [cut, cut_body] = Post(dir_ / "cut.body");
  EXPECT_EQ(cut, 400) << cut_body;
  EXPECT_THAT(cut_body, HasSubstr("close delimiter"));

  // The phantom, whole: 200 with every instance referenced, and the rule's
  // job at once (complete_on_request).
  const std::vector<std::string> phantom = DicomFiles(kPhantom);
  ASSERT_EQ(phantom.size(), 28u);
  WriteBody(dir_ / "phantom.body", phantom);
  auto [ok, ok_body] = Post(dir_ / "phantom.body");
  ASSERT_EQ(ok, 200) << ok_body << server_->Log();
  const nlohmann::json answer = nlohmann::json::parse(ok_body);
  EXPECT_EQ(answer["00081199"]["Value"].size(), 28u);
  nlohmann::json status;
  ASSERT_TRUE(WaitFor(
      [&] {
        status = Status();
        return status.contains("jobs") && !status["jobs"].empty();
      },
      std::chrono::seconds(60), std::chrono::milliseconds(200)))
      << server_->Log();
  ASSERT_EQ(status["jobs"].size(), 1u) << status.dump();
  EXPECT_THAT(status["jobs"][0]["origin"].get<std::string>(),
              HasSubstr("STOW:alice->INTERSLICE rule stow-ct"));
  EXPECT_THAT(server_->Log(), HasSubstr("(28 instance(s))"));

  // Authentication: none or a wrong token -> 401.
  EXPECT_EQ(
      Curl({"-H", kType, "--data-binary", "x", base_ + "/dicomweb/studies"})
          .first,
      401);
  EXPECT_EQ(Curl({"-u", "x:wrong", "-H", kType, "--data-binary", "x",
                  base_ + "/dicomweb/studies"})
                .first,
            401);
  // Methods and paths.
  EXPECT_EQ(Curl({"-u", "x:tok-alice", base_ + "/dicomweb/studies"}).first,
            405);
  for (const std::string path :
       {"/dicomweb/studies/../../etc/passwd", "/dicomweb/studies/1.2/series",
        "/dicomweb/studies/abc", "/dicomweb/", "/dicomweb/studies/1..2"}) {
    EXPECT_EQ(Curl({"-u", "x:tok-alice", "--path-as-is", "-X", "POST", "-H",
                    kType, "--data-binary", "x", base_ + path})
                  .first,
              404)
        << path;
  }
  // A wrong Content-Type: 415.
  EXPECT_EQ(
      Curl({"-u", "x:tok-alice", "-H", "Content-Type: application/json",
            "--data-binary", "@" + phantom[0], base_ + "/dicomweb/studies"})
          .first,
      415);
  // An instance of another study than the path's: 409, 0xA900.
  WriteBody(dir_ / "one.body", {phantom[0]});
  auto [other, other_body] = Post(dir_ / "one.body", "/1.2.3");
  EXPECT_EQ(other, 409) << other_body;
  EXPECT_THAT(other_body, HasSubstr("\"00081197\":{\"Value\":[43264]"));
  // A part that is not DICOM: 409 (none stored), 0xC000.
  {
    std::ofstream(dir_ / "junk.body")
        << "--stow-test-boundary\r\nContent-Type: application/dicom\r\n\r\n"
           "not dicom\r\n--stow-test-boundary--\r\n";
  }
  auto [junk, junk_body] = Post(dir_ / "junk.body");
  EXPECT_EQ(junk, 409) << junk_body;
  EXPECT_THAT(junk_body, HasSubstr("[49152]"));
  // Bodies over --stow-max-body-bytes: 413 by Content-Length (unread), and
  // counted as a chunked body arrives.
  {
    std::ofstream big(dir_ / "big.body", std::ios::binary);
    big << std::string(17000000, 'x');
  }
  EXPECT_EQ(Post(dir_ / "big.body").first, 413);
  EXPECT_EQ(
      Post(dir_ / "big.body", "", {"-H", "Transfer-Encoding: chunked"}).first,
      413);
  // A 10 GB Content-Length from a raw socket: 413 before any body byte.
  {
    const int fd = Connect(http_port_);
    ASSERT_GE(fd, 0);
    const std::string request = absl::StrCat(
        "POST /dicomweb/studies HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
        "tok-alice\r\n",
        kType, "\r\nContent-Length: 10737418240\r\n\r\n");
    ASSERT_EQ(::send(fd, request.data(), request.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(request.size()));
    std::string response;
    EXPECT_TRUE(ClosedByServer(fd, 30000, &response));
    EXPECT_THAT(response, HasSubstr("HTTP/1.1 413 Payload Too Large"));
    ::close(fd);
  }
  // Only the phantom's job was made (the cut series waits, incomplete).
  const nlohmann::json after = Status();
  EXPECT_EQ(after["jobs"].size(), 1u);
  const std::string log = server_->Log();
  // The cut body's whole parts (the last one ends with no delimiter) were
  // kept, but as an incomplete series.
  EXPECT_THAT(log, HasSubstr("HTTP 400, 2 instance(s) kept, 0 refused; "
                             "malformed multipart body"));
  EXPECT_THAT(log, HasSubstr("(2 instance(s)) is incomplete"));
  EXPECT_THAT(log, ::testing::Not(HasSubstr("1.3.46.670589")));
  ASSERT_EQ(server_->Stop(), 0) << log;
  const std::string audit = ReadFileOrEmpty(dir_ / "audit.jsonl");
  EXPECT_THAT(audit, HasSubstr("\"event\":\"stow.received\""));
  EXPECT_THAT(audit, HasSubstr("\"identity\":\"STOW:alice\""));
  EXPECT_THAT(audit, ::testing::Not(HasSubstr("1.3.46.670589")));
}

// Sends `request` on a fresh connection, then (`close_after`) shuts the
// sending side or keeps it open; returns what the server answered within
// 30 s.
std::string RawExchange(int port, const std::string& request,
                        bool close_after) {
  const int fd = Connect(port);
  EXPECT_GE(fd, 0);
  if (fd < 0) return "";
  EXPECT_EQ(::send(fd, request.data(), request.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(request.size()));
  if (close_after) ::shutdown(fd, SHUT_WR);
  std::string answer;
  ClosedByServer(fd, 30000, &answer);
  ::close(fd);
  return answer;
}

// Issue 39, finding 2: a body that holds a whole multipart message but
// fewer bytes than its Content-Length promised was answered 200 and made a
// job when the client kept the connection open (and 400 when it closed).
// Either way the request did not arrive as its sender said it would: 400,
// and its series is incomplete (no job, even with complete_on_request).
TEST_F(StowServerTest, BodyShorterThanItsContentLengthIsNeverWhole) {
  WriteBody(dir_ / "small.body", DicomFiles(kSmallSeries));
  const std::string body = ReadFileOrEmpty(dir_ / "small.body");
  const std::string request = absl::StrCat(
      "POST /dicomweb/studies HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
      "tok-alice\r\n",
      kType, "\r\nContent-Length: ", body.size() + 1, "\r\n\r\n", body);
  for (const bool close_after : {false, true}) {
    const std::string answer = RawExchange(http_port_, request, close_after);
    EXPECT_THAT(answer, HasSubstr("HTTP/1.1 400")) << answer;
    if (!close_after) {
      EXPECT_THAT(answer, HasSubstr("its Content-Length promised")) << answer;
    }
  }
  // The operator sees it waiting, incomplete, on the status page (issue 39,
  // finding 7).
  const nlohmann::json waiting = Status();
  ASSERT_EQ(waiting["series"].size(), 1u) << waiting.dump();
  EXPECT_EQ(waiting["series"][0]["state"], "incomplete");
  EXPECT_EQ(waiting["series"][0]["instances"], 3);
  EXPECT_EQ(waiting["series"][0]["calling_ae"], "STOW:alice");
  EXPECT_THAT(waiting["series"][0]["why"].get<std::string>(),
              HasSubstr("did not arrive whole"));
  EXPECT_TRUE(waiting["jobs"].empty());
  // The same body with its true length is whole: its job is made at once.
  const std::string whole = absl::StrCat(
      "POST /dicomweb/studies HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
      "tok-alice\r\n",
      kType, "\r\nContent-Length: ", body.size(), "\r\n\r\n", body);
  EXPECT_THAT(RawExchange(http_port_, whole, false), HasSubstr("HTTP/1.1 200"));
  nlohmann::json status;
  ASSERT_TRUE(WaitFor(
      [&] {
        status = Status();
        return status.contains("jobs") && !status["jobs"].empty();
      },
      std::chrono::seconds(60), std::chrono::milliseconds(200)))
      << server_->Log();
  // Made of the whole request after the two short ones: the series was
  // incomplete until a whole transfer brought all of it.
  EXPECT_EQ(status["jobs"].size(), 1u) << status.dump();
  const std::string log = server_->Log();
  EXPECT_THAT(log, HasSubstr("(3 instance(s)) is incomplete"));
  EXPECT_THAT(log, HasSubstr("is complete again"));
  ASSERT_EQ(server_->Stop(), 0) << log;
  const std::string audit = ReadFileOrEmpty(dir_ / "audit.jsonl");
  EXPECT_THAT(audit, HasSubstr("not complete"));
}

// A series sent the way many STOW-RS clients send it: one instance per
// request, under the shipped rule's complete_on_release.
class StowGroupingTest : public StowServerTest {
 protected:
  std::string Rules() const override {
    return "stable_seconds: 2\n"
           "rules:\n"
           "  - name: stow-ct\n"
           "    match: {modality: CT, called_ae: INTERSLICE, calling_ae: "
           "\"STOW:alice\"}\n"
           "    job: {threshold: 300}\n"
           "    complete_on_release: true\n";
  }
};

// Issue 39, finding 3: one job per request, each on a part of the series
// (five jobs on 2-6 slices). And finding 6: a single-part application/dicom
// body was 415, a boundary of Orthanc's 73 characters 400, and STOW took SOP
// classes the DIMSE listener refuses.
TEST_F(StowGroupingTest, OneInstancePerRequestMakesOneJobOfTheWholeSeries) {
  const std::vector<std::string> files = DicomFiles(kSmallSeries);
  ASSERT_EQ(files.size(), 3u);
  const std::string url = base_ + "/dicomweb/studies";
  // A single-part body: the instance itself.
  auto [single, single_body] =
      Curl({"-u", "x:tok-alice", "-H", "Content-Type: application/dicom",
            "--data-binary", "@" + files[0], url});
  EXPECT_EQ(single, 200) << single_body << server_->Log();
  // A 73-character boundary, as Orthanc's DICOMweb plugin sends.
  const std::string boundary(73, 'b');
  {
    std::ofstream out(dir_ / "long.body", std::ios::binary);
    out << "--" << boundary << "\r\nContent-Type: application/dicom\r\n\r\n"
        << std::ifstream(files[1], std::ios::binary).rdbuf() << "\r\n--"
        << boundary << "--\r\n";
  }
  auto [long_boundary, long_body] =
      Curl({"-u", "x:tok-alice", "-H",
            "Content-Type: multipart/related; type=\"application/dicom\"; "
            "boundary=" +
                boundary,
            "--data-binary", "@" + (dir_ / "long.body"), url});
  EXPECT_EQ(long_boundary, 200) << long_body;
  // Past the stated limit (256): 400 naming it.
  auto [too_long, too_long_body] = Curl(
      {"-u", "x:tok-alice", "-H",
       "Content-Type: multipart/related; boundary=" + std::string(257, 'b'),
       "--data-binary", "@" + (dir_ / "long.body"), url});
  EXPECT_EQ(too_long, 400);
  EXPECT_THAT(too_long_body, HasSubstr("1-256 characters"));
  WriteBody(dir_ / "third.body", {files[2]});
  EXPECT_EQ(Post(dir_ / "third.body").first, 200);
  // Secondary Capture, which the DIMSE listener does not negotiate: 409,
  // 0x0122 (SOP class not supported), and it makes no series here.
  {
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(OFFilename(files[0].c_str())).good());
    DcmDataset* ds = file.getDataset();
    ds->putAndInsertString(DCM_SOPClassUID, UID_SecondaryCaptureImageStorage);
    ds->putAndInsertString(DCM_SeriesInstanceUID, "1.2.826.0.1.3680043.10.9");
    ds->putAndInsertString(DCM_SOPInstanceUID, "1.2.826.0.1.3680043.10.9.1");
    ASSERT_TRUE(file.saveFile(OFFilename((dir_ / "sc.dcm").c_str())).good());
  }
  WriteBody(dir_ / "sc.body", {dir_ / "sc.dcm"});
  auto [sc, sc_body] = Post(dir_ / "sc.body");
  EXPECT_EQ(sc, 409) << sc_body;
  EXPECT_THAT(sc_body, HasSubstr("\"00081197\":{\"Value\":[290]"));

  nlohmann::json status;
  ASSERT_TRUE(WaitFor(
      [&] {
        status = Status();
        return status.contains("jobs") && !status["jobs"].empty();
      },
      std::chrono::seconds(60), std::chrono::milliseconds(200)))
      << server_->Log();
  // Two more stable waits: still the one job, on all three instances.
  std::this_thread::sleep_for(std::chrono::seconds(4));
  status = Status();
  EXPECT_EQ(status["jobs"].size(), 1u) << status.dump();
  const std::string log = server_->Log();
  EXPECT_THAT(log, HasSubstr("made by rule stow-ct for a series from "
                             "STOW:alice -> INTERSLICE (3 instance(s))"));
  // STOW traffic in /metrics (issue 39, finding 7).
  auto [metrics_code, metrics] = Curl(
      {absl::StrCat("http://127.0.0.1:", server_->metrics_port(), "/metrics")});
  ASSERT_EQ(metrics_code, 200);
  EXPECT_THAT(metrics,
              HasSubstr("interslice_stow_instances_total{outcome=\"stored\"} "
                        "3"));
  EXPECT_THAT(metrics, HasSubstr("interslice_stow_instances_total{outcome="
                                 "\"refused\"} 1"));
  EXPECT_THAT(metrics, HasSubstr("interslice_http_requests_total{code=\"200\","
                                 "route=\"STOW-RS\"} 3"));
  EXPECT_THAT(metrics, HasSubstr("interslice_http_requests_total{code=\"409\","
                                 "route=\"STOW-RS\"} 1"));
  EXPECT_THAT(metrics, HasSubstr("interslice_http_requests_total{code=\"200\","
                                 "route=\"status\"}"));
  ASSERT_EQ(server_->Stop(), 0) << log;
}

// Slow loris: a client that trickles its headers (one byte every 200 ms, so
// never silent for the 2 s request timeout) is cut off while the server
// keeps answering others. (A trickled body is not cut: status_page.h.)
TEST_F(StowServerTest, SlowClientIsCutOffAndOthersServed) {
  const std::string headers = absl::StrCat(
      "POST /dicomweb/studies HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
      "tok-alice\r\n",
      kType, "\r\nContent-Length: 1000000\r\n\r\n");
  const int fd = Connect(http_port_);
  ASSERT_GE(fd, 0);
  size_t sent = 0;
  std::string answer;
  bool closed = false;
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (!closed && std::chrono::steady_clock::now() < deadline &&
         sent < headers.size()) {
    if (::send(fd, headers.data() + sent, 1, MSG_NOSIGNAL) != 1) {
      closed = true;
      break;
    }
    ++sent;
    closed = ClosedByServer(fd, 200, &answer);
    if (sent == 3) {
      // Meanwhile another client is served.
      EXPECT_EQ(Curl({"-u", "x:tok-ops", base_ + "/status.json"}).first, 200);
    }
  }
  EXPECT_TRUE(closed) << sent << " bytes sent and still open";
  EXPECT_LT(sent, headers.size());
  ::close(fd);
  EXPECT_EQ(Curl({"-u", "x:tok-ops", base_ + "/status.json"}).first, 200);
}

// A server that authenticates gRPC callers by client certificate only (no
// tokens) answers STOW-RS with 403: its HTTP listener checks no client
// certificate, so it must not take anonymous instances.
TEST(StowAuthTest, ClientCertificateOnlyServerRefusesStowWith403) {
  TempDir dir;
  const std::string script = absl::StrCat(
      "set -e; cd ", dir.str(), "; exec >openssl.log 2>&1\n",
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=test-ca "
      "-keyout ca.key -out ca.pem\n",
      "openssl req -newkey rsa:2048 -nodes -subj /CN=localhost "
      "-keyout server.key -out server.csr\n",
      "printf 'subjectAltName=IP:127.0.0.1,DNS:localhost\\n' > san.ext\n",
      "openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key "
      "-CAcreateserial -days 2 -extfile san.ext -out server.pem\n",
      "openssl req -newkey rsa:2048 -nodes -subj /CN=client "
      "-keyout client.key -out client.csr\n",
      "openssl x509 -req -in client.csr -CA ca.pem -CAkey ca.key "
      "-CAcreateserial -days 2 -out client.pem\n");
  ASSERT_EQ(RunCommand({"/bin/sh", "-c", script}).exit_code, 0)
      << ReadFileOrEmpty(dir / "openssl.log");
  std::ofstream(dir / "rules.yaml") << "stable_seconds: 600\nrules: []\n";
  const int port = FreeTcpPort();
  ServerProcess server(ServerOptions{
      .spool = dir / "spool",
      .log = dir / "server.log",
      .extra = {"--tls-cert", dir / "server.pem", "--tls-key",
                dir / "server.key", "--tls-client-ca", dir / "ca.pem",
                "--dicom-listen", "127.0.0.1:0", "--rules", dir / "rules.yaml",
                "--http-listen", absl::StrCat("127.0.0.1:", port)},
      .tls_ca_file = dir / "ca.pem",
      .tls_client_cert_file = dir / "client.pem",
      .tls_client_key_file = dir / "client.key"});
  ASSERT_TRUE(server.Start());
  WriteBody(dir / "small.body", DicomFiles(kSmallSeries));
  auto [code, body] =
      Curl({"-H", kType, "--data-binary", "@" + (dir / "small.body"),
            absl::StrCat("http://127.0.0.1:", port, "/dicomweb/studies")});
  EXPECT_EQ(code, 403) << body;
  EXPECT_THAT(body, HasSubstr("client certificate"));
  EXPECT_THAT(server.Log(), ::testing::Not(HasSubstr("dicomweb: STOW")));
}

// HTTPS (--http-tls-cert/--http-tls-key): served with a certificate curl
// checks, when the civetweb and OpenSSL found at run time can; otherwise
// (Debian bookworm: server::HttpTlsAvailable) the server refuses to start
// with the reason instead of crashing at the first handshake.
TEST(StowHttpsTest, HttpsIsServedOrRefusedWithItsReason) {
  TempDir dir;
  const std::string script = absl::StrCat(
      "set -e; cd ", dir.str(), "; exec >openssl.log 2>&1\n",
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=localhost "
      "-addext subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout http.key "
      "-out http.pem\n");
  ASSERT_EQ(RunCommand({"/bin/sh", "-c", script}).exit_code, 0)
      << ReadFileOrEmpty(dir / "openssl.log");
  std::ofstream(dir / "rules.yaml") << "stable_seconds: 600\nrules: []\n";
  const int port = FreeTcpPort();
  ServerProcess server(ServerOptions{
      .spool = dir / "spool",
      .log = dir / "server.log",
      .extra = {"--dicom-listen", "127.0.0.1:0", "--rules", dir / "rules.yaml",
                "--http-listen", absl::StrCat("127.0.0.1:", port),
                "--http-tls-cert", dir / "http.pem", "--http-tls-key",
                dir / "http.key"}});
  const absl::Status available = server::HttpTlsAvailable();
  if (!available.ok()) {
    EXPECT_FALSE(server.Start());
    EXPECT_EQ(server.exit_code(), 1);
    EXPECT_THAT(server.Log(),
                HasSubstr(absl::StrCat("interslice-server: error: ",
                                       available.message())));
    // The refusal points at the proxy deployment, whose example exists.
    EXPECT_THAT(available.message(), HasSubstr("docs/dicomweb.md, \"HTTPS\""));
    EXPECT_THAT(available.message(),
                HasSubstr("docs/examples/stunnel-https.conf"));
    EXPECT_TRUE(
        fs::is_regular_file(std::string(::interslice::testing::SourceDir()) +
                            "/docs/examples/stunnel-https.conf"));
    GTEST_SKIP() << "no HTTPS here: " << available.message();
  }
  ASSERT_TRUE(server.Start());
  WriteBody(dir / "small.body", DicomFiles(kSmallSeries));
  const std::string url =
      absl::StrCat("https://127.0.0.1:", port, "/dicomweb/studies");
  auto [code, body] = Curl({"--cacert", dir / "http.pem", "-H", kType,
                            "--data-binary", "@" + (dir / "small.body"), url});
  EXPECT_EQ(code, 200) << body;
  // Without the CA curl does not trust it; plain HTTP is not served there.
  EXPECT_EQ(Curl({url}).first, 0);
  EXPECT_NE(Curl({absl::StrCat("http://127.0.0.1:", port, "/status")}).first,
            200);
}

}  // namespace
}  // namespace interslice::testing
