// End-to-end tests of the DICOM listener: real interslice-server processes on
// loopback (ports from --port-file), driven by DCMTK's own tools (echoscu,
// storescu) and by the `interslice` client.
#include <arpa/inet.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <thread>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "interslice/spool/v1/record.pb.h"
#include "tests/server/net/dimse/raw_pdu.h"
#include "tests/testing/files.h"
#include "tests/testing/made_elsewhere.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/tools.h"
#include "tests/testing/wait_for.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
namespace raw = interslice::testing;  // raw_pdu.h: PDUs byte by byte
using ::testing::HasSubstr;

const std::string kCli = ::interslice::testing::CliPath();
// DCMTK's tools (Debian package dcmtk, in install-deps.sh).
const std::string kEchoScu = "/usr/bin/echoscu";
const std::string kStoreScu = "/usr/bin/storescu";
const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";
// A small job on the phantom: a 96 x 96 region of all 28 slices.
const char kJobYaml[] =
    "{threshold: 300, roi: [208, 208, 0, 304, 304, 28], mesh: [stl], "
    "volume: [nii], previews: [png, dicom]}";
const std::vector<std::string> kJobArgs = {
    "--threshold", "300",      "--roi", "208,208,0,304,304,28", "--mesh",
    "stl",         "--volume", "nii",   "--previews",           "png,dicom"};

std::vector<std::string> PhantomFiles() {
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(kPhantom)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  return files;
}

void WriteFile(const std::string& path, const std::string& text) {
  std::ofstream(path) << text;
}

// Peers: storescu/echoscu call as STORESCU / ECHOSCU by default.
std::string WritePeers(const TempDir& dir) {
  const std::string path = dir / "peers.yaml";
  WriteFile(path,
            "peers:\n"
            "  - {name: tools, ae_title: STORESCU, host: 127.0.0.1, port: 1}\n"
            "  - {name: echo, ae_title: ECHOSCU, host: 127.0.0.1, port: 1}\n");
  return path;
}

std::string WriteRules(const TempDir& dir, double stable_seconds,
                       bool complete_on_release) {
  const std::string path = dir / "rules.yaml";
  WriteFile(path,
            absl::StrCat("stable_seconds: ", stable_seconds,
                         "\nrules:\n"
                         "  - name: not-mr\n"
                         "    match: {modality: MR}\n"
                         "    job: {threshold: 1}\n"
                         "  - name: ct-head\n"
                         "    match: {modality: CT, called_ae: INTERSLICE, "
                         "calling_ae: STORESCU, slice_count: {min: 20}}\n"
                         "    job: ",
                         kJobYaml, "\n    complete_on_release: ",
                         complete_on_release ? "true" : "false", "\n"));
  return path;
}

// How a test server is started besides its flags.
struct ServerSetup {
  std::string listen = "0.0.0.0:0";  // --dicom-listen
  // Non-empty: the spool is a tmpfs of this size ("6m") in a mount
  // namespace of the server's own (unshare -m), so that its disk can fill.
  std::string tmpfs_size;
  // More "NAME:TOKEN" lines for the token file (identities besides admin).
  std::string extra_tokens;
};

// A server with the DICOM listener (and an admin token, so that the test
// lists every job), in `dir`/`name`. The lifecycle is the shared fixture's
// (tests/testing/server_process.h); this adds what the DICOM tests look at.
class DicomServer {
 public:
  DicomServer(const TempDir& dir, const std::string& name,
              std::vector<std::string> extra, ServerSetup setup = {})
      : token_file_(dir / "admin.token"),
        setup_(setup),
        server_(Options(dir, name, std::move(extra), setup)) {
    std::ofstream(dir / "admin.tokens") << "admin:admin-token\n"
                                        << setup.extra_tokens;
    std::ofstream(token_file_) << "admin-token\n";
    started_ = server_.Start();
  }
  // Whether it started (on failure: why, and the log's end).
  ::testing::AssertionResult up() const {
    if (!started_) return started_;
    if (server_.dicom_port() <= 0) {
      return ::testing::AssertionFailure() << "no DICOM port in the port file";
    }
    return ::testing::AssertionSuccess();
  }
  // The exit code once the server ended by itself (e.g. a bad
  // configuration), waiting up to `wait_seconds`; -1 while it runs.
  int ExitCode(double wait_seconds) { return server_.WaitExit(wait_seconds); }
  // kill -9, as a crash or a power cut would end it.
  void Kill() { server_.Kill(); }
  // SIGTERM: the drain; the exit code (-1: killed after `wait_seconds`).
  int Terminate(double wait_seconds) { return server_.Stop(wait_seconds); }
  bool running() const { return server_.running(); }
  pid_t pid() const { return server_.pid(); }
  std::string port() const { return std::to_string(server_.dicom_port()); }
  std::vector<std::string> Client() const {
    return Cat(server_.ServerFlag(), {"--token-file", token_file_});
  }
  std::string Log() const { return server_.Log(); }
  const std::string& spool() const { return server_.spool(); }
  // The spool as the server sees it (its own tmpfs, when it has one).
  std::string SpoolView() const {
    if (setup_.tmpfs_size.empty() || !server_.running()) return spool();
    return absl::StrCat("/proc/", server_.pid(), "/root", spool());
  }

  // Instances waiting in series folders.
  int PendingInstances() const {
    int n = 0;
    std::error_code ec;
    for (const auto& e : fs::recursive_directory_iterator(
             fs::path(SpoolView()) / "dicom-in" / "series", ec)) {
      if (e.path().extension() == ".dcm") ++n;
    }
    return n;
  }

  // A counter of /metrics (the whole sample name with its labels, e.g.
  // interslice_dicom_events_total{event="associations"}); -1 if absent.
  double Metric(const std::string& sample) const {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(server_.metrics_port()));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
      ::close(fd);
      return -1;
    }
    const std::string request = "GET /metrics HTTP/1.0\r\n\r\n";
    (void)!::write(fd, request.data(), request.size());
    std::string body;
    char buffer[65536];
    ssize_t n;
    while ((n = ::read(fd, buffer, sizeof(buffer))) > 0) body.append(buffer, n);
    ::close(fd);
    for (absl::string_view line : absl::StrSplit(body, '\n')) {
      if (absl::StartsWith(line, sample + " ")) {
        double v = 0;
        if (absl::SimpleAtod(line.substr(sample.size() + 1), &v)) return v;
      }
    }
    return -1;
  }
  double Refused(const std::string& reason) const {
    const double v = Metric(absl::StrCat(
        "interslice_dicom_connections_refused_total{reason=\"", reason, "\"}"));
    return v < 0 ? 0 : v;
  }

  // Job ids the server lists (admin view).
  std::vector<std::string> Jobs() const {
    CommandResult list = RunCommand(Cat({kCli, "list", "--all"}, Client()), 60);
    std::vector<std::string> ids;
    for (absl::string_view line : absl::StrSplit(list.out, '\n')) {
      // A job's own line; its details follow indented.
      if (line.empty() || line[0] == ' ') continue;
      std::vector<std::string> words =
          absl::StrSplit(line, ' ', absl::SkipEmpty());
      if (!words.empty()) ids.push_back(words[0]);
    }
    return ids;
  }

 private:
  static ServerOptions Options(const TempDir& dir, const std::string& name,
                               std::vector<std::string> extra,
                               const ServerSetup& setup) {
    ServerOptions options{
        .spool = dir / name,
        .log = dir / (name + ".log"),
        .extra =
            Cat({"--metrics-listen", "127.0.0.1:0", "--auth-token-file",
                 dir / "admin.tokens", "--admin-identity", "admin",
                 "--dicom-listen", setup.listen, "--dicom-acse-timeout", "3"},
                extra),
        .threads_per_job = 1};
    if (!setup.tmpfs_size.empty()) {
      std::error_code ec;
      fs::create_directories(options.spool, ec);
      options.command_prefix = {"/usr/bin/unshare",
                                "-m",
                                "--propagation",
                                "private",
                                "/bin/sh",
                                "-c",
                                "mount -t tmpfs -o size=" + setup.tmpfs_size +
                                    " tmpfs \"$0\" && exec \"$@\"",
                                options.spool};
    }
    return options;
  }

  std::string token_file_;
  ServerSetup setup_;
  ServerProcess server_;
  ::testing::AssertionResult started_ = ::testing::AssertionFailure();
};

// Polls `done` (up to `seconds`).
bool WaitUntil(const std::function<bool()>& done, double seconds) {
  return WaitFor(done, std::chrono::duration<double>(seconds),
                 std::chrono::milliseconds(100));
}

CommandResult StoreScu(const DicomServer& server,
                       const std::vector<std::string>& options,
                       const std::vector<std::string>& files) {
  return RunCommand(Cat(Cat(Cat({kStoreScu}, options),
                            {"-aec", "INTERSLICE", "127.0.0.1", server.port()}),
                        files),
                    120);
}

TEST(DicomNodeTest, EchoAndAssociationPolicy) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 30, false),
       "--dicom-ae", "INTERSLICE", "--dicom-ae", "INTERSLICE_MR"});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult ok =
      RunCommand({kEchoScu, "-aec", "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(ok.exit_code, 0) << ok.err;
  // A second called AE title is served too.
  CommandResult second = RunCommand(
      {kEchoScu, "-aec", "INTERSLICE_MR", "127.0.0.1", server.port()});
  EXPECT_EQ(second.exit_code, 0) << second.err;
  CommandResult unknown_caller =
      RunCommand({kEchoScu, "-aet", "STRANGER", "-aec", "INTERSLICE",
                  "127.0.0.1", server.port()});
  EXPECT_NE(unknown_caller.exit_code, 0);
  EXPECT_THAT(unknown_caller.err, HasSubstr("Association Rejected"));
  EXPECT_THAT(unknown_caller.err, HasSubstr("Calling AE Title Not Recognized"));
  CommandResult unknown_called = RunCommand(
      {kEchoScu, "-aec", "SOMEONE_ELSE", "127.0.0.1", server.port()});
  EXPECT_NE(unknown_called.exit_code, 0);
  EXPECT_THAT(unknown_called.err, HasSubstr("Called AE Title Not Recognized"));
  EXPECT_THAT(server.Log(),
              HasSubstr("calling AE title STRANGER is not in the peers file"));
}

int PortOf(const sockaddr_in& address) { return ntohs(address.sin_port); }

// TCP_NODELAY (0 or 1) of the IPv4 TCP socket of process `pid` whose own
// port is `local_port` and whose peer's is `remote_port`: each of its
// descriptors is copied into this process (pidfd_getfd, Linux 5.6) and
// asked. -1 when it has no such socket (yet).
int NoDelayOfSocketIn(pid_t pid, int local_port, int remote_port) {
  const int pidfd = static_cast<int>(::syscall(SYS_pidfd_open, pid, 0));
  if (pidfd < 0) return -1;
  int result = -1;
  std::error_code ec;
  for (const auto& entry :
       fs::directory_iterator(absl::StrCat("/proc/", pid, "/fd"), ec)) {
    const std::string target = fs::read_symlink(entry.path(), ec).string();
    if (ec || !absl::StartsWith(target, "socket:")) continue;
    int number = 0;
    if (!absl::SimpleAtoi(entry.path().filename().string(), &number)) continue;
    const int fd =
        static_cast<int>(::syscall(SYS_pidfd_getfd, pidfd, number, 0));
    if (fd < 0) continue;
    sockaddr_in local{}, remote{};
    socklen_t local_len = sizeof(local), remote_len = sizeof(remote);
    int nodelay = 0;
    socklen_t nodelay_len = sizeof(nodelay);
    if (::getsockname(fd, reinterpret_cast<sockaddr*>(&local), &local_len) ==
            0 &&
        local.sin_family == AF_INET && PortOf(local) == local_port &&
        ::getpeername(fd, reinterpret_cast<sockaddr*>(&remote), &remote_len) ==
            0 &&
        PortOf(remote) == remote_port &&
        ::getsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &nodelay, &nodelay_len) ==
            0) {
      result = nodelay != 0 ? 1 : 0;
    }
    ::close(fd);
    if (result >= 0) break;
  }
  ::close(pidfd);
  return result;
}

// Issue 25: with Nagle's algorithm on, every DIMSE exchange waits ~40 ms for
// a delayed acknowledgement. The listener's accepted sockets and the
// server's outgoing associations (here a C-GET pull, DcmSCU: the same
// connect path as delivery's DcmStorageSCU) must have TCP_NODELAY set. The
// outgoing one is DCMTK's: without DisableNagleOnOutgoingAssociations() in
// main() this reads 0.
TEST(DicomNodeTest, NagleIsOffOnAcceptedAndOutgoingAssociations) {
  TempDir dir;
  // A "PACS" that accepts the server's connection and says nothing.
  const int listener = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  ASSERT_GE(listener, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(
      ::bind(listener, reinterpret_cast<sockaddr*>(&address), sizeof(address)),
      0);
  ASSERT_EQ(::listen(listener, 4), 0);
  socklen_t len = sizeof(address);
  ::getsockname(listener, reinterpret_cast<sockaddr*>(&address), &len);
  const int pacs_port = PortOf(address);
  WriteFile(dir / "peers.yaml",
            absl::StrCat("peers:\n"
                         "  - {name: pacs, ae_title: PACS, host: 127.0.0.1, "
                         "port: ",
                         pacs_port, "}\n"));
  // No TCP_NODELAY inherited from whoever runs the tests.
  ASSERT_EQ(::unsetenv("TCP_NODELAY"), 0);
  DicomServer server(dir, "spool", {"--dicom-peers", dir / "peers.yaml"});
  ASSERT_TRUE(server.up()) << server.Log();

  // Accepted: a connection that has not sent its request yet.
  const int client = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in dicom{};
  dicom.sin_family = AF_INET;
  dicom.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  dicom.sin_port = htons(static_cast<uint16_t>(std::stoi(server.port())));
  ASSERT_EQ(
      ::connect(client, reinterpret_cast<sockaddr*>(&dicom), sizeof(dicom)), 0);
  sockaddr_in client_address{};
  len = sizeof(client_address);
  ::getsockname(client, reinterpret_cast<sockaddr*>(&client_address), &len);
  int accepted = -1;
  EXPECT_TRUE(WaitUntil(
      [&] {
        accepted = NoDelayOfSocketIn(server.pid(), std::stoi(server.port()),
                                     PortOf(client_address));
        return accepted >= 0;
      },
      60));
  EXPECT_EQ(accepted, 1) << "the listener's accepted socket has Nagle on";
  ::close(client);

  // Outgoing: the pull connects to our silent PACS.
  const CommandResult submit =
      RunCommand(Cat(Cat({kCli, "submit", "--threshold", "300", "--pacs",
                          "pacs", "--study", "1.2.3", "--series", "1.2.3.4"},
                         server.Client()),
                     {}),
                 60);
  ASSERT_EQ(submit.exit_code, 0) << submit.err << server.Log();
  pollfd waiting{listener, POLLIN, 0};
  ASSERT_TRUE(WaitUntil([&] { return ::poll(&waiting, 1, 0) == 1; }, 120))
      << "the server never connected to the peer\n"
      << server.Log();
  sockaddr_in server_side{};
  len = sizeof(server_side);
  const int connection = ::accept4(
      listener, reinterpret_cast<sockaddr*>(&server_side), &len, SOCK_CLOEXEC);
  ASSERT_GE(connection, 0);
  int outgoing = -1;
  EXPECT_TRUE(WaitUntil(
      [&] {
        outgoing =
            NoDelayOfSocketIn(server.pid(), PortOf(server_side), pacs_port);
        return outgoing >= 0;
      },
      60));
  EXPECT_EQ(outgoing, 1) << "the outgoing association's socket has Nagle on";
  ::close(connection);
  ::close(listener);
}

TEST(DicomNodeTest, UnknownCallersAcceptedWhenThePeersFileSaysSo) {
  TempDir dir;
  WriteFile(dir / "open.yaml", "accept_unknown_callers: true\npeers: []\n");
  DicomServer server(dir, "spool", {"--dicom-peers", dir / "open.yaml"});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult r = RunCommand({kEchoScu, "-aet", "ANYONE", "-aec",
                                "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(r.exit_code, 0) << r.err;
}

// Found by dicom_listener_fuzzer (fuzz_cases/empty-calling-ae-leak.bin): an
// association request whose calling AE title is empty (PS3.8 9.3.2 forbids
// it) was accepted when unknown callers are, and DCMTK 3.6.7 could not build
// the A-ASSOCIATE-AC for it: 64 bytes leaked and the association aborted.
// It is rejected now, with its reason, and the server serves on.
TEST(DicomNodeTest,
     EmptyOrNonAsciiCallingAeTitleIsRejectedEvenWhenAnyCallerIsAccepted) {
  TempDir dir;
  WriteFile(dir / "open.yaml", "accept_unknown_callers: true\npeers: []\n");
  DicomServer server(dir, "spool", {"--dicom-peers", dir / "open.yaml"});
  ASSERT_TRUE(server.up()) << server.Log();
  const int fd = raw::Connect(std::stoi(server.port()));
  ASSERT_GE(fd, 0);
  ASSERT_TRUE(raw::SendAll(
      fd, raw::AssociateRq("INTERSLICE", "",
                           {{1,
                             UID_VerificationSOPClass,
                             {UID_LittleEndianImplicitTransferSyntax}}})));
  std::optional<raw::Pdu> answer = raw::ReadPdu(fd, 30);
  ::close(fd);
  ASSERT_TRUE(answer.has_value()) << server.Log();
  EXPECT_EQ(answer->type, 0x03) << "not an A-ASSOCIATE-RJ";
  EXPECT_TRUE(WaitUntil([&] { return server.Refused("calling_ae") >= 1; }, 30))
      << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("calling AE title is empty"));
  // Found by the fuzzer next (fuzz_cases/non-ascii-calling-ae-crash.bin): a
  // calling AE title with bytes outside the default repertoire was accepted
  // and its first instance stopped the server (origin.json is UTF-8 JSON).
  const int second = raw::Connect(std::stoi(server.port()));
  ASSERT_GE(second, 0);
  ASSERT_TRUE(raw::SendAll(
      second, raw::AssociateRq("INTERSLICE",
                               "ST\xb7\xad\xba\xac"
                               "CU",
                               {{1,
                                 UID_CTImageStorage,
                                 {UID_LittleEndianExplicitTransferSyntax}}})));
  answer = raw::ReadPdu(second, 30);
  ::close(second);
  ASSERT_TRUE(answer.has_value()) << server.Log();
  EXPECT_EQ(answer->type, 0x03) << "not an A-ASSOCIATE-RJ";
  EXPECT_TRUE(WaitUntil([&] { return server.Refused("calling_ae") >= 2; }, 30))
      << server.Log();
  EXPECT_THAT(server.Log(),
              HasSubstr("calling AE title has a character outside the default "
                        "repertoire"));
  CommandResult r = RunCommand({kEchoScu, "-aet", "ANYONE", "-aec",
                                "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(r.exit_code, 0) << r.err;
}

TEST(DicomNodeTest, InvalidRulesFileStopsTheServerWithOneLine) {
  TempDir dir;
  WriteFile(dir / "bad.yaml",
            "rules:\n  - name: ct\n    job: {threshold: 300, method: fast}\n");
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", dir / "bad.yaml"});
  EXPECT_EQ(server.ExitCode(30), 1);
  EXPECT_THAT(server.Log(),
              HasSubstr("bad.yaml: rule 'ct' (#1): job.method: unknown method "
                        "'fast'"));
  // A rule bound to an AE title the server does not answer to.
  WriteFile(dir / "ae.yaml",
            "rules:\n  - name: mr\n    match: {called_ae: NOT_OURS}\n"
            "    job: {threshold: 1}\n");
  DicomServer second(
      dir, "spool2",
      {"--dicom-peers", WritePeers(dir), "--rules", dir / "ae.yaml"});
  EXPECT_EQ(second.ExitCode(30), 1);
  EXPECT_THAT(second.Log(),
              HasSubstr("rule 'mr' (#1): match.called_ae: NOT_OURS"));
}

// The shipped phantom, sent with storescu, makes a job by rule whose
// artifacts equal `interslice run` on the same files with the same options.
TEST(DicomNodeTest, PhantomSentWithStorescuMakesTheRulesJob) {
  TempDir dir;
  CommandResult local =
      RunCommand(Cat(Cat({kCli, "run", kPhantom}, kJobArgs),
                     {"--out", dir / "local", "--quiet", "--threads", "1"}),
                 300);
  ASSERT_EQ(local.exit_code, 0) << local.err;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 1.5, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  ASSERT_EQ(files.size(), 28u);
  CommandResult store = StoreScu(server, {}, files);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  std::vector<std::string> jobs;
  ASSERT_TRUE(WaitUntil(
      [&] {
        jobs = server.Jobs();
        return !jobs.empty();
      },
      120))
      << server.Log();
  ASSERT_EQ(jobs.size(), 1u);
  CommandResult watch = RunCommand(
      Cat({kCli, "watch", jobs[0], "--quiet"}, server.Client()), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  CommandResult fetch = RunCommand(
      Cat({kCli, "fetch", jobs[0], "--out", dir / "remote"}, server.Client()),
      120);
  ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
  // Every file, the previews' included (4 PNG, 4 DICOM): the same bytes
  // (DICOM files: the same size; their creation times differ).
  ExpectSameFiles(dir / "local", dir / "remote", 12, {},
                  DicomComparison::kSameSize);
  EXPECT_TRUE(fs::exists(dir / "remote/previews-dicom/IM00004.dcm"));
  const std::string log = server.Log();
  EXPECT_THAT(log, HasSubstr("made by rule ct-head"));
  EXPECT_THAT(log, HasSubstr("STORESCU -> INTERSLICE released: 28 instance(s) "
                             "kept, 0 refused"));
  // The job records where it came from (JobStatus.origin).
  EXPECT_THAT(ReadFileOrEmpty(server.spool() + "/jobs/" + jobs[0] + "/job.pb"),
              HasSubstr("dicom:STORESCU->INTERSLICE rule ct-head"));
  // `list` says where the job came from and which series it read, UIDs
  // included (the server runs without authentication: one anonymous user,
  // who may see every job).
  CommandResult list =
      RunCommand(Cat({kCli, "list", "--all"}, server.Client()), 60);
  ASSERT_EQ(list.exit_code, 0) << list.err;
  EXPECT_THAT(list.out,
              HasSubstr("origin    DICOM from STORESCU to INTERSLICE, rule "
                        "ct-head\n"));
  EXPECT_THAT(list.out, HasSubstr("input     CT, 28 instance(s)\n"));
  DcmFileFormat first;
  ASSERT_TRUE(first.loadFile(OFFilename(files[0].c_str())).good());
  OFString study, series;
  first.getDataset()->findAndGetOFString(DCM_StudyInstanceUID, study);
  first.getDataset()->findAndGetOFString(DCM_SeriesInstanceUID, series);
  ASSERT_FALSE(study.empty());
  EXPECT_THAT(list.out,
              HasSubstr(absl::StrCat("study     ", study.c_str(), "\n")));
  EXPECT_THAT(list.out,
              HasSubstr(absl::StrCat("series    ", series.c_str(), "\n")));
  EXPECT_THAT(list.out, ::testing::ContainsRegex(
                            "times     created 20[0-9-]+ [0-9:]+Z, started "
                            "20[0-9-]+ [0-9:]+Z, finished 20[0-9-]+ [0-9:]+Z"));
  // Nothing was left behind in the DICOM spool.
  EXPECT_EQ(server.PendingInstances(), 0);
  // No UID of the phantom reaches the log.
  EXPECT_THAT(log, ::testing::Not(HasSubstr("1.3.46.670589")));
}

// The pixel data of every instance in a derived series folder, in file name
// order (empty if the folder holds none or one cannot be read).
std::vector<std::string> SeriesPixels(const std::string& folder) {
  std::vector<std::string> files;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(folder, ec)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  std::vector<std::string> pixels;
  for (const std::string& file : files) {
    DcmFileFormat dicom;
    DcmElement* element = nullptr;
    Uint8* bytes = nullptr;
    if (!dicom.loadFile(OFFilename(file.c_str())).good() ||
        !dicom.getDataset()->findAndGetElement(DCM_PixelData, element).good() ||
        !element->getUint8Array(bytes).good() || bytes == nullptr) {
      return {};
    }
    pixels.emplace_back(reinterpret_cast<const char*>(bytes),
                        element->getLength());
  }
  return pixels;
}

// A rule's intensity_method reaches the job it makes: the derived intensity
// series of a rule asking for `linear` (the default is morph) is, pixel for
// pixel, the one `run --intensity-method linear` writes, and not morph's.
TEST(DicomNodeTest, RuleIntensityMethodReachesTheDerivedSeries) {
  TempDir dir;
  const std::vector<std::string> job = {
      "--threshold", "300",       "--roi", "208,208,0,304,304,28", "--mesh",
      "none",        "--volume",  "none",  "--output-series",      "intensity",
      "--quiet",     "--threads", "1"};
  for (const std::string method : {"linear", "morph"}) {
    CommandResult local = RunCommand(
        Cat(Cat({kCli, "run", kPhantom}, job),
            {"--intensity-method", method, "--out", dir / ("local-" + method)}),
        300);
    ASSERT_EQ(local.exit_code, 0) << local.err;
  }
  const std::vector<std::string> linear =
      SeriesPixels(dir / "local-linear/series-intensity");
  const std::vector<std::string> morph =
      SeriesPixels(dir / "local-morph/series-intensity");
  ASSERT_GT(linear.size(), 28u);  // the key slices and those inserted
  ASSERT_EQ(linear.size(), morph.size());
  ASSERT_NE(linear, morph);  // else the test could not see the key dropped
  const std::string rules = dir / "rules.yaml";
  WriteFile(rules,
            "stable_seconds: 1.5\n"
            "rules:\n"
            "  - name: ct-linear\n"
            "    match: {modality: CT, calling_ae: STORESCU}\n"
            "    job: {threshold: 300, roi: [208, 208, 0, 304, 304, 28], "
            "mesh: none, volume: none, output_series: [intensity], "
            "intensity_method: linear}\n");
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules", rules});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult store = StoreScu(server, {}, PhantomFiles());
  ASSERT_EQ(store.exit_code, 0) << store.err;
  std::vector<std::string> jobs;
  ASSERT_TRUE(WaitUntil(
      [&] {
        jobs = server.Jobs();
        return !jobs.empty();
      },
      120))
      << server.Log();
  ASSERT_EQ(jobs.size(), 1u);
  CommandResult watch = RunCommand(
      Cat({kCli, "watch", jobs[0], "--quiet"}, server.Client()), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  CommandResult fetch = RunCommand(
      Cat({kCli, "fetch", jobs[0], "--out", dir / "remote"}, server.Client()),
      120);
  ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
  EXPECT_THAT(server.Log(), HasSubstr("made by rule ct-linear"));
  const std::vector<std::string> remote =
      SeriesPixels(dir / "remote/series-intensity");
  ASSERT_EQ(remote.size(), linear.size());
  EXPECT_TRUE(remote == linear);
  EXPECT_FALSE(remote == morph);
}

// complete_on_release: a normal release completes the series at once; an
// aborted association leaves its instances waiting with their series.
TEST(DicomNodeTest, ReleaseCompletesAtOnceAbortKeepsTheInstances) {
  TempDir dir;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 600, true)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  CommandResult aborted = StoreScu(server, {"--abort"}, files);
  EXPECT_EQ(aborted.exit_code, 0) << aborted.err;
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("aborted: 28 instance(s) kept") !=
               std::string::npos;
      },
      120))
      << server.Log();
  // A check that nothing happens: 1 s later the aborted association's
  // instances still wait and made no job (a sleep, not a wait).
  std::this_thread::sleep_for(std::chrono::seconds(1));
  EXPECT_EQ(server.PendingInstances(), 28);
  EXPECT_TRUE(server.Jobs().empty());
  // The same series again, released: complete at once (not after 600 s),
  // the re-sent instances replace themselves.
  CommandResult released = StoreScu(server, {}, files);
  EXPECT_EQ(released.exit_code, 0) << released.err;
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 120))
      << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("(28 instance(s))"));
  EXPECT_EQ(server.PendingInstances(), 0);
}

TEST(DicomNodeTest, InstancesSurviveARestartAndCompleteAfterIt) {
  TempDir dir;
  const std::vector<std::string> flags = {
      "--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false)};
  {
    DicomServer server(dir, "spool", flags);
    ASSERT_TRUE(server.up()) << server.Log();
    CommandResult store = StoreScu(server, {}, PhantomFiles());
    ASSERT_EQ(store.exit_code, 0) << store.err;
    EXPECT_EQ(server.PendingInstances(), 28);
  }
  WriteRules(dir, 1, false);  // shorter wait after the restart
  DicomServer again(dir, "spool", flags);
  ASSERT_TRUE(again.up()) << again.Log();
  EXPECT_THAT(again.Log(), HasSubstr("1 series received before the restart"));
  ASSERT_TRUE(WaitUntil([&] { return !again.Jobs().empty(); }, 120))
      << again.Log();
}

TEST(DicomNodeTest, UnsupportedTransferSyntaxIsRefusedInNegotiation) {
  TempDir dir;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 600, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  // MPEG2 only (storescu -xm, -R: only the SOP classes of the files): no
  // core decoder, so no storage context is accepted and the association is
  // rejected in negotiation; nothing is sent.
  CommandResult r = StoreScu(server, {"-xm", "-R"}, {PhantomFiles().front()});
  EXPECT_NE(r.exit_code, 0);
  EXPECT_THAT(r.out + r.err, HasSubstr("Association Rejected"));
  EXPECT_EQ(server.PendingInstances(), 0);
  // The same file proposed in explicit little endian is taken.
  CommandResult control =
      StoreScu(server, {"-xe", "-R"}, {PhantomFiles().front()});
  EXPECT_EQ(control.exit_code, 0) << control.err;
  EXPECT_EQ(server.PendingInstances(), 1);
}

TEST(DicomNodeTest, FullSpoolAnswersOutOfResourcesAndKeepsNothingUnacked) {
  TempDir dir;
  // Room for a few of the 532 KiB phantom slices only.
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false),
       "--spool-quota-bytes", "3000000"});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult r = StoreScu(server, {"-v", "-nh"}, PhantomFiles());
  const std::string out = r.out + r.err;
  const int kept = server.PendingInstances();
  // storescu's words for 0xA700 and for success, one per instance.
  auto count = [&out](const std::string& what) {
    int n = 0;
    for (size_t at = out.find(what); at != std::string::npos;
         at = out.find(what, at + 1)) {
      ++n;
    }
    return n;
  };
  EXPECT_EQ(count("Received Store Response (Refused: OutOfResources)"),
            28 - kept)
      << out;
  EXPECT_EQ(count("Received Store Response (Success)"), kept) << out;
  EXPECT_GT(kept, 0);
  EXPECT_LT(kept, 28);
  // Every acknowledged instance is on disk; the refused ones are not, and
  // no partial file is left in the staging folder.
  EXPECT_THAT(server.Log(), HasSubstr(absl::StrCat(kept, " instance(s) kept, ",
                                                   28 - kept, " refused")));
  int staged = 0;
  for (const auto& e : fs::directory_iterator(fs::path(server.spool()) /
                                              "dicom-in" / "incoming")) {
    (void)e;
    ++staged;
  }
  EXPECT_EQ(staged, 0);
}

// A series that takes most of the spool quota still becomes its job: its
// received bytes are handed over to the job's upload, not counted twice.
TEST(DicomNodeTest, SeriesNearTheQuotaStillBecomesItsJob) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, true),
       "--spool-quota-bytes", "20000000"});  // the phantom is 14.9 MB
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult store = StoreScu(server, {}, PhantomFiles());
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 120))
      << server.Log();
  EXPECT_EQ(server.PendingInstances(), 0);
}

// An instance larger than a whole series may be is cut off while it
// streams in (the association is aborted), not written to the end first.
TEST(DicomNodeTest, OversizeInstanceIsCutOffWhileStreaming) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false),
       "--dicom-max-series-bytes", "100000"});  // a phantom slice is 532 KiB
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult r = StoreScu(server, {}, {PhantomFiles().front()});
  EXPECT_NE(r.exit_code, 0);
  EXPECT_THAT(r.err, HasSubstr("Peer aborted Association"));
  // The cut-off is logged while the instance streams in; the partial file
  // is removed after that, before the association ends: wait for its end.
  EXPECT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("aborted: 0 instance(s) kept, 0 refused") !=
               std::string::npos;
      },
      120))
      << server.Log();
  EXPECT_THAT(server.Log(),
              HasSubstr("aborted: an instance passed 100000 bytes"));
  EXPECT_EQ(server.PendingInstances(), 0);
  int staged = 0;
  for (const auto& e : fs::directory_iterator(fs::path(server.spool()) /
                                              "dicom-in" / "incoming")) {
    (void)e;
    ++staged;
  }
  EXPECT_EQ(staged, 0);
  // Others are served as before.
  CommandResult echo = RunCommand({kEchoScu, "-aet", "STORESCU", "-aec",
                                   "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(echo.exit_code, 0) << echo.err;
}

int ConnectTo(int port) {
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

TEST(DicomNodeTest, GarbageAndSilentPeersCostOnlyTheirOwnAssociation) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false),
       "--dicom-dimse-timeout", "3"});
  ASSERT_TRUE(server.up()) << server.Log();
  const int port = std::stoi(server.port());
  // Garbage: not a PDU at all, and a PDU header claiming 4 GiB.
  const int garbage = ConnectTo(port);
  ASSERT_GE(garbage, 0);
  const std::string junk = "GET / HTTP/1.1\r\nHost: x\r\n\r\n";
  ASSERT_EQ(::write(garbage, junk.data(), junk.size()),
            static_cast<ssize_t>(junk.size()));
  const int huge = ConnectTo(port);
  ASSERT_GE(huge, 0);
  const unsigned char header[] = {0x01, 0x00, 0xff, 0xff, 0xff, 0xff};
  ASSERT_EQ(::write(huge, header, sizeof(header)),
            static_cast<ssize_t>(sizeof(header)));
  // A connection that never says anything.
  const int silent = ConnectTo(port);
  ASSERT_GE(silent, 0);
  // Others are still served (a silent peer holds the accepting thread for
  // at most the ACSE timeout, 3 s here).
  CommandResult echo = RunCommand(
      {kEchoScu, "-to", "30", "-aec", "INTERSLICE", "127.0.0.1", server.port()},
      60);
  EXPECT_EQ(echo.exit_code, 0) << echo.err;
  CommandResult store = StoreScu(server, {}, {PhantomFiles().front()});
  EXPECT_EQ(store.exit_code, 0) << store.err;
  EXPECT_EQ(server.PendingInstances(), 1);
  ::close(garbage);
  ::close(huge);
  ::close(silent);
  // And the server is still healthy afterwards.
  CommandResult again =
      RunCommand({kEchoScu, "-aec", "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(again.exit_code, 0) << again.err;
}

void MakeCertificates(const TempDir& dir) {
  const std::string script = absl::StrCat(
      "set -e; cd ", dir.str(), "; exec >openssl.log 2>&1\n",
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=test-ca "
      "-keyout ca.key -out ca.pem\n",
      "for who in server client; do\n"
      "  openssl req -newkey rsa:2048 -nodes -subj /CN=$who "
      "-keyout $who.key -out $who.csr\n"
      "  openssl x509 -req -in $who.csr -CA ca.pem -CAkey ca.key "
      "-CAcreateserial -days 2 -out $who.pem\n"
      "done\n",
      // A certificate from a CA the server does not trust.
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=rogue "
      "-keyout rogue.key -out rogue.pem\n");
  ASSERT_EQ(RunCommand({"/bin/sh", "-c", script}).exit_code, 0)
      << ReadFileOrEmpty(dir / "openssl.log");
}

TEST(DicomNodeTest, TlsWithCaCheckedCertificates) {
  TempDir dir;
  MakeCertificates(dir);
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false),
       "--dicom-tls-cert", dir / "server.pem", "--dicom-tls-key",
       dir / "server.key", "--dicom-tls-ca", dir / "ca.pem"});
  ASSERT_TRUE(server.up()) << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("with TLS"));
  auto tls = [&](const std::string& who) {
    return std::vector<std::string>{"+tls", dir / (who + ".key"),
                                    dir / (who + ".pem"), "+cf",
                                    dir / "ca.pem"};
  };
  CommandResult echo =
      RunCommand(Cat(Cat({kEchoScu}, tls("client")),
                     {"-aec", "INTERSLICE", "127.0.0.1", server.port()}));
  EXPECT_EQ(echo.exit_code, 0) << echo.err;
  CommandResult store = StoreScu(server, tls("client"), PhantomFiles());
  EXPECT_EQ(store.exit_code, 0) << store.err;
  EXPECT_EQ(server.PendingInstances(), 28);
  // Plain TCP, and a certificate no trusted CA signed, are refused.
  CommandResult plain = RunCommand(
      {kEchoScu, "-to", "10", "-aec", "INTERSLICE", "127.0.0.1", server.port()},
      60);
  EXPECT_NE(plain.exit_code, 0);
  CommandResult rogue =
      RunCommand(Cat(Cat({kEchoScu, "-to", "10"}, tls("rogue")),
                     {"-aec", "INTERSLICE", "127.0.0.1", server.port()}),
                 60);
  EXPECT_NE(rogue.exit_code, 0);
  // The listener still serves good peers afterwards.
  CommandResult again =
      RunCommand(Cat(Cat({kEchoScu}, tls("client")),
                     {"-aec", "INTERSLICE", "127.0.0.1", server.port()}));
  EXPECT_EQ(again.exit_code, 0) << again.err;
}

// The documented examples are what docs/dicom-node.md shows; the server
// starts with them (so the docs cannot rot).
TEST(DicomNodeTest, DocumentedExamplesStartAServer) {
  TempDir dir;
  const std::string examples =
      std::string(::interslice::testing::SourceDir()) + "/docs/examples";
  DicomServer server(dir, "spool",
                     {"--dicom-peers", examples + "/peers.yaml", "--rules",
                      examples + "/rules.yaml", "--dicom-ae", "INTERSLICE",
                      "--dicom-ae", "INTERSLICE_3D"});
  ASSERT_TRUE(server.up()) << server.Log();
}

// ---- Issue 22: the DICOM edge -------------------------------------------

// A raw association calling as `calling` that proposes CT storage (context
// 1, explicit VR little endian) and Verification (context 3). The socket
// after the A-ASSOCIATE-AC, or -1.
int RawAssociate(int port, const std::string& calling = "STORESCU",
                 const std::string& source = "127.0.0.1") {
  const int fd = raw::Connect(port, source);
  if (fd < 0) return -1;
  const std::string rq = raw::AssociateRq(
      "INTERSLICE", calling,
      {{1, UID_CTImageStorage, {UID_LittleEndianExplicitTransferSyntax}},
       {3,
        UID_VerificationSOPClass,
        {UID_LittleEndianImplicitTransferSyntax}}});
  std::optional<raw::Pdu> ac;
  if (raw::SendAll(fd, rq)) ac = raw::ReadPdu(fd, 30);
  if (!ac.has_value() || ac->type != 0x02) {
    ::close(fd);
    return -1;
  }
  return fd;
}

// C-STORE of `dataset` (explicit VR little endian) on context 1, in PDUs of
// at most 16000 bytes. The response's status, or -1 when the connection was
// cut instead.
int RawStore(int fd, const std::string& sop_instance,
             const std::string& dataset, uint16_t message_id = 1) {
  std::string bytes =
      raw::PData(1, true, true,
                 raw::CStoreRq(message_id, UID_CTImageStorage, sop_instance));
  for (size_t at = 0; at < dataset.size(); at += 16000) {
    bytes += raw::PData(1, false, at + 16000 >= dataset.size(),
                        dataset.substr(at, 16000));
  }
  raw::SendAll(fd, bytes);  // may fail half-way: the answer says
  std::optional<raw::Pdu> response = raw::ReadPdu(fd, 60);
  if (!response.has_value()) return -1;
  return raw::ResponseStatus(*response);
}

// The SOP Instance UID of a DICOM file.
std::string SopInstanceOf(const std::string& path) {
  DcmFileFormat file;
  OFString uid;
  if (file.loadFile(OFFilename(path.c_str())).good()) {
    file.getDataset()->findAndGetOFString(DCM_SOPInstanceUID, uid);
  }
  return uid.c_str();
}

// A sender caught by a crash: stores files[0, count) on a raw association
// (`*stored`: how many were answered 0x0000), then sends the command and
// the first half of the next instance's data set and stops, the
// association open. The socket, or -1.
int StorePartOfSeries(const DicomServer& server,
                      const std::vector<std::string>& files, int count,
                      int* stored) {
  *stored = 0;
  const int fd = RawAssociate(std::stoi(server.port()));
  if (fd < 0) return -1;
  for (int i = 0; i < count; ++i) {
    const int status =
        RawStore(fd, SopInstanceOf(files[i]), raw::DatasetOf(files[i]), i + 1);
    if (status == 0x0000) ++*stored;
  }
  const std::string next = raw::DatasetOf(files[count]);
  std::string bytes = raw::PData(1, true, true,
                                 raw::CStoreRq(count + 1, UID_CTImageStorage,
                                               SopInstanceOf(files[count])));
  for (size_t at = 0; at < next.size() / 2; at += 16000) {
    bytes += raw::PData(1, false, false, next.substr(at, 16000));
  }
  raw::SendAll(fd, bytes);
  return fd;
}

CommandResult Echo(const DicomServer& server,
                   const std::vector<std::string>& options = {}) {
  return RunCommand(Cat(Cat({kEchoScu, "-to", "10", "-ta", "10"}, options),
                        {"-aec", "INTERSLICE", "127.0.0.1", server.port()}),
                    60);
}

// Finding 1: one C-STORE with 10,000 nested sequences (360 KB) overflowed
// the stack of DCMTK's parser on the association thread and took the whole
// server down. It is refused (0xC000) on its own association, which goes
// on; the server serves others.
TEST(DicomEdgeTest, HostileNestedInstanceIsRefusedAndTheServerLives) {
  TempDir dir;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 600, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  const int fd = RawAssociate(std::stoi(server.port()));
  ASSERT_GE(fd, 0) << server.Log();
  const std::string hostile =
      raw::NestedDataset("1.2.826.0.1.3680043.2.1125.7", 10000);
  ASSERT_GT(hostile.size(), 350000u);
  EXPECT_EQ(RawStore(fd, "1.2.826.0.1.3680043.2.1125.7", hostile), 0xC000)
      << server.Log();
  // The same association still stores a real instance.
  EXPECT_EQ(RawStore(fd, "1.2.826.0.1.3680043.2.1125.8",
                     raw::DatasetOf(PhantomFiles().front()), 2),
            0x0000);
  raw::SendAll(fd, raw::ReleaseRq());
  raw::ReadPdu(fd, 10);
  ::close(fd);
  EXPECT_TRUE(server.running());
  EXPECT_EQ(Echo(server).exit_code, 0);
  EXPECT_THAT(server.Log(), HasSubstr("nesting deeper than 32 sequences"));
  EXPECT_EQ(server.Metric(
                "interslice_dicom_events_total{event=\"instances_refused\"}"),
            1);
  EXPECT_EQ(server.PendingInstances(), 1);
}

// The command set is parsed on the association thread too: a command with
// nested sequences is cut at its first element outside group 0000, before
// DCMTK has it; only its connection ends.
TEST(DicomEdgeTest, NestedCommandSetCutsOnlyItsConnection) {
  TempDir dir;
  DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)});
  ASSERT_TRUE(server.up()) << server.Log();
  const int fd = RawAssociate(std::stoi(server.port()));
  ASSERT_GE(fd, 0) << server.Log();
  const std::string command = raw::CStoreRq(1, UID_CTImageStorage, "1.2.3") +
                              raw::NestedDataset("1.2.3", 10000);
  std::string bytes;
  for (size_t at = 0; at < command.size(); at += 16000) {
    bytes += raw::PData(1, true, at + 16000 >= command.size(),
                        command.substr(at, 16000));
  }
  raw::SendAll(fd, bytes);
  // No response: the connection is closed (perhaps after an A-ABORT).
  std::optional<raw::Pdu> answer = raw::ReadPdu(fd, 30);
  EXPECT_TRUE(!answer.has_value() || answer->type == 0x07);
  ::close(fd);
  EXPECT_TRUE(server.running());
  EXPECT_EQ(Echo(server).exit_code, 0) << server.Log();
  EXPECT_TRUE(
      WaitUntil([&] { return server.Refused("protocol_violation") >= 1; }, 10))
      << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("outside group 0000"));
}

// Finding 2: a sender killed after some instances made a job (and results)
// of what had arrived, complete_on_release or not. Now the series waits
// incomplete; the sender's retry makes exactly one job, of all 28.
TEST(DicomEdgeTest, SenderKilledMidSeriesMakesNoJobUntilItIsComplete) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 1, true)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  // The sender stops half-way into instance 13 and its socket closes, as
  // when the process is killed (a storescu killed after a timed wait could
  // finish first: it sends the 28 slices in tens of milliseconds).
  int stored = 0;
  const int fd = StorePartOfSeries(server, files, 12, &stored);
  ASSERT_GE(fd, 0) << server.Log();
  ASSERT_EQ(stored, 12) << server.Log();
  ::close(fd);
  ASSERT_TRUE(WaitUntil(
      [&] { return server.Log().find("is incomplete") != std::string::npos; },
      30))
      << server.Log();
  // Well past the stable wait: still no job.
  std::this_thread::sleep_for(std::chrono::seconds(3));
  EXPECT_TRUE(server.Jobs().empty()) << server.Log();
  EXPECT_EQ(server.Metric(
                "interslice_dicom_events_total{event=\"series_incomplete\"}"),
            1);
  // The retry: one job, of the whole series.
  CommandResult store = StoreScu(server, {}, files);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 60))
      << server.Log();
  std::this_thread::sleep_for(std::chrono::seconds(2));
  EXPECT_EQ(server.Jobs().size(), 1u);
  EXPECT_THAT(server.Log(), HasSubstr("(28 instance(s))"));
  EXPECT_THAT(server.Log(), HasSubstr("is complete again"));
}

// Issue 39, finding 1: a transfer cut half-way, then one instance of it
// stored again, byte for byte the same, in a clean association: the log
// said "is complete again after a later transfer of it" and a job ran on
// half the series. A re-sent instance proves nothing about the missing
// part: the series stays incomplete, and the remainder completes it.
TEST(DicomEdgeTest, ReSentInstanceNeverCompletesAnIncompleteSeries) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 1, true)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  int stored = 0;
  const int fd = StorePartOfSeries(server, files, 14, &stored);
  ASSERT_GE(fd, 0) << server.Log();
  ASSERT_EQ(stored, 14) << server.Log();
  ::close(fd);
  ASSERT_TRUE(WaitUntil(
      [&] { return server.Log().find("is incomplete") != std::string::npos; },
      30))
      << server.Log();
  // One instance of it again, unchanged, in an association released
  // normally; then another one.
  for (const int i : {0, 5}) {
    CommandResult again = StoreScu(server, {}, {files[i]});
    ASSERT_EQ(again.exit_code, 0) << again.err;
  }
  EXPECT_TRUE(WaitUntil(
      [&] {
        return server.Metric(
                   "interslice_dicom_events_total{event=\""
                   "series_resend_not_completing\"}") == 2;
      },
      30))
      << server.Log();
  // Well past the stable wait (1 s): still no job.
  std::this_thread::sleep_for(std::chrono::seconds(3));
  EXPECT_TRUE(server.Jobs().empty()) << server.Log();
  EXPECT_THAT(server.Log(), ::testing::Not(HasSubstr("is complete again")));
  // Finding 7: the operator sees it, with why and how much of it arrived.
  CommandResult kept =
      RunCommand(Cat({kCli, "kept", "list"}, server.Client()), 60);
  ASSERT_EQ(kept.exit_code, 0) << kept.err;
  EXPECT_THAT(kept.out, HasSubstr("  incomplete "));
  EXPECT_THAT(kept.out, HasSubstr("14 instance(s)"));
  EXPECT_THAT(kept.out, HasSubstr("without a normal release"));
  // The remainder: one job, of all 28.
  CommandResult rest = StoreScu(
      server, {}, std::vector<std::string>(files.begin() + 14, files.end()));
  ASSERT_EQ(rest.exit_code, 0) << rest.err;
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 60))
      << server.Log();
  EXPECT_EQ(server.Jobs().size(), 1u);
  EXPECT_THAT(server.Log(), HasSubstr("(28 instance(s))"));
  EXPECT_THAT(server.Log(), HasSubstr("is complete again"));
}

// Issue 39, finding 4: the node's own results sent back to it (a PACS
// routing rule, or README's "send every series" run a second time) were
// processed again as a new source: results of results. They make no job
// unless a rule asks for them with own_results: true.
TEST(DicomEdgeTest, OwnResultsSentBackMakeNoJobUnlessARuleAsks) {
  TempDir dir;
  CommandResult made = RunCommand(
      {kCli, "run",
       std::string(::interslice::testing::SourceDir()) + "/tests/data/ct-thick",
       "--threshold", "300", "--method", "linear", "--output-series",
       "intensity", "--mesh", "none", "--volume", "none", "--previews", "none",
       "--quiet", "--out", dir / "results"},
      300);
  ASSERT_EQ(made.exit_code, 0) << made.err;
  std::vector<std::string> results;
  for (const auto& e :
       fs::directory_iterator(dir / "results/series-intensity")) {
    results.push_back(e.path().string());
  }
  ASSERT_FALSE(results.empty());
  const std::string job =
      "{threshold: 300, method: linear, mesh: none, volume: [nii], "
      "previews: none}";
  const std::string rules = dir / "own.yaml";
  WriteFile(rules, absl::StrCat("stable_seconds: 0.5\nrules:\n"
                                "  - name: any-ct\n"
                                "    match: {modality: CT}\n"
                                "    job: ",
                                job, "\n"));
  {
    DicomServer server(dir, "spool",
                       {"--dicom-peers", WritePeers(dir), "--rules", rules});
    ASSERT_TRUE(server.up()) << server.Log();
    ASSERT_EQ(StoreScu(server, {}, results).exit_code, 0);
    // Counted where the job would have been made; without the count (as
    // before the fix), the wait ends after 30 s and the job is there.
    EXPECT_TRUE(WaitUntil(
        [&] {
          return server.Metric(
                     "interslice_dicom_events_total{event=\""
                     "own_results_not_run\"}") == 1;
        },
        30))
        << server.Log();
    EXPECT_TRUE(server.Jobs().empty()) << server.Log();
    EXPECT_THAT(server.Log(), HasSubstr("made by interslice (its own result"));
  }
  // A rule that asks for them takes them (and only them: the CT rule
  // before it still does not).
  WriteFile(rules, absl::StrCat("stable_seconds: 0.5\nrules:\n"
                                "  - name: any-ct\n"
                                "    match: {modality: CT}\n"
                                "    job: ",
                                job,
                                "\n  - name: results-again\n"
                                "    match: {own_results: true}\n"
                                "    job: ",
                                job, "\n"));
  DicomServer again(dir, "spool2",
                    {"--dicom-peers", WritePeers(dir), "--rules", rules});
  ASSERT_TRUE(again.up()) << again.Log();
  ASSERT_EQ(StoreScu(again, {}, results).exit_code, 0);
  ASSERT_TRUE(WaitUntil([&] { return !again.Jobs().empty(); }, 60))
      << again.Log();
  EXPECT_THAT(again.Log(), HasSubstr("made by rule results-again"));
}

// Issue 39, finding 7: a sender at its per-source limit that associated
// again the moment its release was answered was refused ("local limit
// exceeded"): its place was freed only after the worker had cleaned up.
// It is freed as the release begins.
TEST(DicomEdgeTest, SenderAtItsLimitMayAssociateAgainAtOnce) {
  TempDir dir;
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WritePeers(dir), "--rules", WriteRules(dir, 600, false),
       "--dicom-max-associations-per-source", "1"});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  for (int i = 0; i < 4; ++i) {
    CommandResult store = StoreScu(server, {}, {files[i]});
    ASSERT_EQ(store.exit_code, 0)
        << "store " << i << ": " << store.err << server.Log();
  }
  // Tighter than a process can be: the next association is requested the
  // moment the A-RELEASE-RP is read, while the first socket is still open.
  const int port = std::stoi(server.port());
  int fd = RawAssociate(port);
  ASSERT_GE(fd, 0) << server.Log();
  for (int i = 0; i < 30; ++i) {
    ASSERT_TRUE(raw::SendAll(fd, raw::ReleaseRq()));
    const std::optional<raw::Pdu> rp = raw::ReadPdu(fd, 30);
    ASSERT_TRUE(rp.has_value() && rp->type == 0x06) << "release " << i;
    const int next = RawAssociate(port);
    ::close(fd);
    ASSERT_GE(next, 0) << "association " << i + 1
                       << " right after a release was refused\n"
                       << server.Log();
    fd = next;
  }
  ::close(fd);
  EXPECT_EQ(server.Refused("associations_per_source"), 0) << server.Log();
}

// Issue 39, finding 7: a command set whose CommandGroupLength lies about
// its length held an association slot for the whole DIMSE timeout (60 s).
// It is cut as soon as its last fragment has arrived.
TEST(DicomEdgeTest, LyingCommandSetIsCutAtOnce) {
  TempDir dir;
  DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)});
  ASSERT_TRUE(server.up()) << server.Log();
  const int fd = RawAssociate(std::stoi(server.port()));
  ASSERT_GE(fd, 0) << server.Log();
  std::string command = raw::CEchoRq(1);
  command[8] = static_cast<char>(static_cast<unsigned char>(command[8]) + 40);
  const auto t0 = std::chrono::steady_clock::now();
  raw::SendAll(fd, raw::PData(3, true, true, command));
  // No answer: the connection is closed (perhaps after an A-ABORT).
  std::optional<raw::Pdu> answer = raw::ReadPdu(fd, 30);
  EXPECT_TRUE(!answer.has_value() || answer->type == 0x07);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
          .count();
  ::close(fd);
  EXPECT_LT(seconds, 20) << "held until a timeout";
  EXPECT_TRUE(
      WaitUntil([&] { return server.Refused("protocol_violation") >= 1; }, 10))
      << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("CommandGroupLength says"));
  EXPECT_EQ(Echo(server).exit_code, 0) << server.Log();
}

// Finding 2, the server's side: killed while an association stores into a
// series, it finds the series incomplete after the restart.
TEST(DicomEdgeTest, ServerKilledMidAssociationLeavesTheSeriesIncomplete) {
  TempDir dir;
  const std::vector<std::string> flags = {"--dicom-peers", WritePeers(dir),
                                          "--rules", WriteRules(dir, 1, true)};
  const std::vector<std::string> files = PhantomFiles();
  {
    DicomServer server(dir, "spool", flags);
    ASSERT_TRUE(server.up()) << server.Log();
    int stored = 0;
    const int fd = StorePartOfSeries(server, files, 12, &stored);
    ASSERT_GE(fd, 0) << server.Log();
    ASSERT_EQ(stored, 12) << server.Log();
    server.Kill();  // mid-association, mid-instance
    ::close(fd);
  }
  DicomServer again(dir, "spool", flags);
  ASSERT_TRUE(again.up()) << again.Log();
  EXPECT_THAT(again.Log(), HasSubstr("1 of them interrupted mid-association"));
  std::this_thread::sleep_for(std::chrono::seconds(3));
  EXPECT_TRUE(again.Jobs().empty()) << again.Log();
  CommandResult store = StoreScu(again, {}, files);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil([&] { return !again.Jobs().empty(); }, 60))
      << again.Log();
  EXPECT_THAT(again.Log(), HasSubstr("(28 instance(s))"));
}

// Finding 3: one connection sending its association request a byte at a
// time held every new association back; here, while one dribbles, others
// are served at once, and it is cut at the ACSE timeout (3 s), counted.
TEST(DicomEdgeTest, SlowRequestDoesNotHoldOthersBackAndIsCut) {
  TempDir dir;
  DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)});
  ASSERT_TRUE(server.up()) << server.Log();
  const int port = std::stoi(server.port());
  const std::string rq =
      raw::AssociateRq("INTERSLICE", "ECHOSCU",
                       {{1,
                         UID_VerificationSOPClass,
                         {UID_LittleEndianImplicitTransferSyntax}}});
  const int slow = raw::Connect(port);
  ASSERT_GE(slow, 0);
  std::atomic<bool> cut{false};
  std::thread dribble([&] {
    for (size_t i = 0; i < rq.size() && !cut; ++i) {
      if (!raw::SendAll(slow, rq.substr(i, 1))) cut = true;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  // Served while the slow one dribbles (echoscu gives up after 10 s).
  for (int i = 0; i < 3; ++i) {
    CommandResult echo = Echo(server);
    EXPECT_EQ(echo.exit_code, 0) << echo.err << server.Log();
  }
  EXPECT_TRUE(
      WaitUntil([&] { return server.Refused("request_deadline") >= 1; }, 30))
      << server.Log();
  cut = true;
  dribble.join();
  ::close(slow);
  EXPECT_THAT(server.Log(),
              HasSubstr("the association request was not complete within 3 s"));
}

// Finding 3: 50 connections that say nothing filled the association limit
// ("Local Limit Exceeded") for 20 s. They cost no association now: a real
// sender is served, and every one of them is counted when it is closed.
TEST(DicomEdgeTest, HalfOpenFloodDoesNotTakeTheAssociations) {
  TempDir dir;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 600, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  const int port = std::stoi(server.port());
  std::vector<int> flood;
  for (int i = 0; i < 50; ++i) {
    const int fd = raw::Connect(port);
    ASSERT_GE(fd, 0);
    flood.push_back(fd);
  }
  CommandResult echo = Echo(server);
  EXPECT_EQ(echo.exit_code, 0) << echo.err << server.Log();
  CommandResult store = StoreScu(server, {}, {PhantomFiles().front()});
  EXPECT_EQ(store.exit_code, 0) << store.err << server.Log();
  EXPECT_EQ(server.PendingInstances(), 1);
  // Each of the 50 made way for a newer connection or reached the deadline.
  auto counted = [&] {
    return server.Refused("pending_per_source") +
           server.Refused("pending_total") + server.Refused("request_deadline");
  };
  EXPECT_TRUE(WaitUntil([&] { return counted() >= 50; }, 30))
      << counted() << "\n"
      << server.Log();
  EXPECT_EQ(counted(), 50);
  for (int fd : flood) ::close(fd);
}

// Finding 4: --dicom-listen 127.0.0.1:PORT listened on every interface.
TEST(DicomEdgeTest, ListensOnExactlyTheAddressGiven) {
  TempDir dir;
  ServerSetup setup;
  setup.listen = "127.0.0.2:0";  // loopback, but not 127.0.0.1
  DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)}, setup);
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult there = RunCommand({kEchoScu, "-to", "10", "-aec", "INTERSLICE",
                                    "127.0.0.2", server.port()});
  EXPECT_EQ(there.exit_code, 0) << there.err;
  CommandResult elsewhere =
      RunCommand({kEchoScu, "-to", "10", "-aec", "INTERSLICE", "127.0.0.1",
                  server.port()});
  EXPECT_NE(elsewhere.exit_code, 0);
  EXPECT_THAT(server.Log(), HasSubstr("listening on 127.0.0.2 port"));
}

// Finding 4: a peer was trusted by its AE title alone. allowed_sources in
// the peers file binds it to addresses.
TEST(DicomEdgeTest, AllowedSourcesOfAPeerAreEnforced) {
  TempDir dir;
  WriteFile(dir / "peers.yaml",
            "peers:\n"
            "  - {name: far, ae_title: STORESCU, host: 10.1.1.1,\n"
            "     allowed_sources: [10.1.0.0/16]}\n"
            "  - {name: near, ae_title: NEAR, host: 127.0.0.2,\n"
            "     allowed_sources: [127.0.0.2]}\n"
            "  - {name: echo, ae_title: ECHOSCU, host: 127.0.0.1}\n");
  DicomServer server(dir, "spool", {"--dicom-peers", dir / "peers.yaml"});
  ASSERT_TRUE(server.up()) << server.Log();
  const int port = std::stoi(server.port());
  CommandResult wrong_host = Echo(server, {"-aet", "STORESCU"});
  EXPECT_NE(wrong_host.exit_code, 0);
  EXPECT_THAT(wrong_host.err, HasSubstr("Calling AE Title Not Recognized"));
  EXPECT_EQ(Echo(server).exit_code, 0);  // ECHOSCU: from anywhere
  const int near = RawAssociate(port, "NEAR", "127.0.0.2");
  EXPECT_GE(near, 0);
  if (near >= 0) ::close(near);
  EXPECT_LT(RawAssociate(port, "NEAR", "127.0.0.1"), 0);
  EXPECT_EQ(server.Refused("calling_address"), 2);
  EXPECT_THAT(server.Log(), HasSubstr("is not allowed from this address"));
}

// Finding 4: a taken DICOM port crashed the server at start (exit 139, no
// message); a crashed predecessor's TIME_WAIT connections did too, so a
// supervisor crash-looped.
TEST(DicomEdgeTest, TakenPortIsOneLineAndTimeWaitIsNot) {
  TempDir dir;
  const int taken = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(taken, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)), 0);
  ASSERT_EQ(::listen(taken, 4), 0);
  socklen_t len = sizeof(addr);
  ::getsockname(taken, reinterpret_cast<sockaddr*>(&addr), &len);
  const std::string port = std::to_string(ntohs(addr.sin_port));
  ServerSetup setup;
  setup.listen = "127.0.0.1:" + port;
  {
    DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)}, setup);
    EXPECT_EQ(server.ExitCode(30), 1) << server.Log();
    EXPECT_THAT(server.Log(),
                HasSubstr("cannot listen for DICOM on 127.0.0.1:" + port +
                          ": the address is in use"));
  }
  ::close(taken);
  // The port is free now. A server on it that closes connections itself
  // (rejected associations) leaves them in TIME_WAIT on its side; killed
  // and started again at once, it must come up.
  {
    DicomServer first(dir, "spool2", {"--dicom-peers", WritePeers(dir)}, setup);
    ASSERT_TRUE(first.up()) << first.Log();
    for (int i = 0; i < 3; ++i) {
      EXPECT_NE(Echo(first, {"-aet", "STRANGER"}).exit_code, 0);
    }
    first.Kill();
  }
  DicomServer second(dir, "spool3", {"--dicom-peers", WritePeers(dir)}, setup);
  ASSERT_TRUE(second.up()) << second.Log();
  EXPECT_EQ(Echo(second).exit_code, 0);
}

// Finding 5: ENOSPC while receiving aborted the association instead of
// answering 0xA700. With the spool on a small tmpfs (and no quota of its
// own to stop it first), every instance gets its answer: success while
// there is room, then "out of resources"; nothing half-written is kept.
TEST(DicomEdgeTest, FullDiskAnswersOutOfResourcesAndKeepsTheAssociation) {
  if (RunCommand({"/usr/bin/unshare", "-m", "/bin/true"}).exit_code != 0) {
    // In CI a missing namespace is a failure (the test must not pass
    // without testing); elsewhere, e.g. a container without CAP_SYS_ADMIN,
    // a skip that names why.
    if (InCi()) FAIL() << "unshare -m fails: cannot make a small spool";
    GTEST_SKIP() << "no mount namespace here (unshare -m): cannot make a "
                    "small file system for the spool";
  }
  TempDir dir;
  ServerSetup setup;
  setup.tmpfs_size = "6m";  // about ten 532 KiB phantom slices
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 600, false)},
                     setup);
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult r = StoreScu(server, {"-v", "-nh"}, PhantomFiles());
  const std::string out = r.out + r.err;
  EXPECT_EQ(r.exit_code, 0) << out;
  EXPECT_THAT(out, ::testing::Not(HasSubstr("Peer aborted Association")));
  auto count = [&out](const std::string& what) {
    int n = 0;
    for (size_t at = out.find(what); at != std::string::npos;
         at = out.find(what, at + 1)) {
      ++n;
    }
    return n;
  };
  const int ok = count("Received Store Response (Success)");
  const int full = count("Received Store Response (Refused: OutOfResources)");
  EXPECT_EQ(ok + full, 28) << out;
  EXPECT_GT(ok, 0);
  EXPECT_GT(full, 0);
  EXPECT_EQ(server.PendingInstances(), ok);
  EXPECT_THAT(server.Log(), HasSubstr("the disk is full"));
  // The series lost instances: it is incomplete, never a job.
  EXPECT_THAT(server.Log(), HasSubstr("is incomplete"));
}

// Finding 5: a job whose output hit a full spool failed INTERNAL with the
// server's spool path in the client's message.
TEST(DicomEdgeTest, JobOnAFullSpoolFailsDiskFullWithoutPaths) {
  if (RunCommand({"/usr/bin/unshare", "-m", "/bin/true"}).exit_code != 0) {
    if (InCi()) FAIL() << "unshare -m fails: cannot make a small spool";
    GTEST_SKIP() << "no mount namespace here (unshare -m)";
  }
  TempDir dir;
  ServerSetup setup;
  // The phantom's 28 slices (14.9 MB) fit; the job's uncompressed volume
  // at factor 8 and its mesh do not.
  setup.tmpfs_size = "17m";
  DicomServer server(dir, "spool", {"--isolation", "thread"}, setup);
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult submit = RunCommand(
      Cat(Cat({kCli, "submit", kPhantom, "--threshold", "300", "--factor", "8",
               "--method", "linear", "--volume", "nrrd", "--mesh", "stl"},
              server.Client()),
          {}),
      300);
  ASSERT_EQ(submit.exit_code, 0) << submit.err << server.Log();
  const std::string id(absl::StripAsciiWhitespace(submit.out));
  CommandResult watch =
      RunCommand(Cat({kCli, "watch", id, "--quiet"}, server.Client()), 300);
  EXPECT_NE(watch.exit_code, 0);
  const std::string said = watch.out + watch.err;
  EXPECT_THAT(said, HasSubstr("disk full")) << said << server.Log();
  EXPECT_THAT(said, ::testing::Not(HasSubstr(server.spool())));
  // The code the job failed with (the client prints the message only).
  spool::v1::JobRecord record;
  std::ifstream in(server.SpoolView() + "/jobs/" + id + "/job.pb",
                   std::ios::binary);
  ASSERT_TRUE(record.ParseFromIstream(&in));
  EXPECT_EQ(record.status().error_code(),
            8);  // RESOURCE_EXHAUSTED
}

// Finding 6: a drain ("no new jobs") still made and ran DICOM jobs. A
// series whose association ends during the drain is kept for after the
// restart instead.
TEST(DicomEdgeTest, DrainMakesNoDicomJobs) {
  TempDir dir;
  // The drain waits for the open association until the DIMSE timeout cuts
  // it: 10 s rather than the default 60 s (what is checked is that nothing
  // of it makes a job, not how long the wait is).
  const std::vector<std::string> flags = {
      "--dicom-peers",          WritePeers(dir),         "--rules",
      WriteRules(dir, 1, true), "--dicom-dimse-timeout", "10"};
  const std::vector<std::string> files = PhantomFiles();
  {
    DicomServer server(dir, "spool", flags);
    ASSERT_TRUE(server.up()) << server.Log();
    // An association open, mid-instance, when the drain begins (a timed
    // storescu could finish first).
    int stored = 0;
    const int fd = StorePartOfSeries(server, files, 3, &stored);
    ASSERT_GE(fd, 0) << server.Log();
    ASSERT_EQ(stored, 3) << server.Log();
    EXPECT_EQ(server.Terminate(120), 0) << server.Log();
    ::close(fd);
    EXPECT_THAT(server.Log(), ::testing::Not(HasSubstr("made by rule")));
  }
  DicomServer again(dir, "spool", flags);
  ASSERT_TRUE(again.up()) << again.Log();
  std::this_thread::sleep_for(std::chrono::seconds(3));  // past stable_seconds
  EXPECT_TRUE(again.Jobs().empty()) << again.Log();
  // The sender's retry after the restart: one job, of the whole series.
  CommandResult store = StoreScu(again, {}, files);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil([&] { return !again.Jobs().empty(); }, 60))
      << again.Log();
  EXPECT_THAT(again.Log(), HasSubstr("(28 instance(s))"));
}

// Finding 6: "grew after its job was made" was logged for a series that
// never had a job (no rule matched it).
TEST(DicomEdgeTest, GrowthIsCalledAfterAJobOnlyWhenThereWasOne) {
  TempDir dir;
  // Two slices: ct-head wants 20 or more, so no rule takes them.
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 0.5, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::vector<std::string> files = PhantomFiles();
  ASSERT_EQ(StoreScu(server, {}, {files[0], files[1]}).exit_code, 0);
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("no rule of rule set") != std::string::npos;
      },
      30))
      << server.Log();
  ASSERT_EQ(StoreScu(server, {}, {files[2]}).exit_code, 0);
  ASSERT_TRUE(WaitUntil(
      [&] {
        const std::string log = server.Log();
        return log.find("grew") != std::string::npos ||
               log.find("received more instances") != std::string::npos;
      },
      30))
      << server.Log();
  EXPECT_THAT(server.Log(),
              ::testing::Not(HasSubstr("after its job was made")));
  EXPECT_THAT(server.Log(), HasSubstr("held without a job"));
  EXPECT_TRUE(server.Jobs().empty());
}

// Finding 6: refused C-FIND/C-MOVE/C-GET associations were not counted in
// associations_rejected.
TEST(DicomEdgeTest, QueryRetrieveAssociationsAreCountedAsRejected) {
  TempDir dir;
  DicomServer server(dir, "spool", {"--dicom-peers", WritePeers(dir)});
  ASSERT_TRUE(server.up()) << server.Log();
  // Every event docs/dicom-node.md names is exposed from the start (at 0),
  // so a dashboard's rate() has a series before the first one happens.
  for (const char* event :
       {"series_resent_unchanged", "instances_other_frame_of_reference",
        "instances_moved", "series_incomplete_dropped"}) {
    EXPECT_EQ(server.Metric(absl::StrCat(
                  "interslice_dicom_events_total{event=\"", event, "\"}")),
              0)
        << event;
  }
  const std::vector<std::string> query = {
      "-S",         "-k",        "QueryRetrieveLevel=STUDY",
      "-aet",       "STORESCU",  "-aec",
      "INTERSLICE", "127.0.0.1", server.port()};
  EXPECT_NE(RunCommand(Cat({"/usr/bin/findscu"}, query)).exit_code, 0);
  EXPECT_NE(RunCommand(Cat({"/usr/bin/movescu", "-aem", "STORESCU"}, query))
                .exit_code,
            0);
  // getscu proposes storage contexts for its sub-operations besides C-GET:
  // the association is accepted without the C-GET context, and getscu
  // gives up by itself; the refused context is counted.
  EXPECT_NE(RunCommand(Cat({"/usr/bin/getscu"}, query)).exit_code, 0);
  EXPECT_EQ(server.Metric("interslice_dicom_events_total{event="
                          "\"associations_rejected\"}"),
            2);
  EXPECT_EQ(server.Refused("no_presentation_context"), 2);
  EXPECT_GE(server.Metric("interslice_dicom_events_total{event="
                          "\"presentation_contexts_refused\"}"),
            1);
  EXPECT_THAT(server.Log(),
              HasSubstr("C-FIND, C-MOVE and C-GET are not served"));
}

// Issue 22: with TLS the handshake is DCMTK's, in an association worker;
// one that starts and stalls is cut at the ACSE timeout like a slow
// request (the deadline runs from the connection), while others are served.
TEST(DicomEdgeTest, StalledTlsHandshakeIsCutAtTheDeadline) {
  TempDir dir;
  MakeCertificates(dir);
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--dicom-tls-cert",
                      dir / "server.pem", "--dicom-tls-key", dir / "server.key",
                      "--dicom-tls-ca", dir / "ca.pem"});
  ASSERT_TRUE(server.up()) << server.Log();
  // The first bytes of a TLS record header, then nothing.
  const int stalled = raw::Connect(std::stoi(server.port()));
  ASSERT_GE(stalled, 0);
  ASSERT_TRUE(raw::SendAll(stalled, std::string("\x16\x03\x01", 3)));
  const std::vector<std::string> tls = {
      "+tls", dir / "client.key", dir / "client.pem", "+cf", dir / "ca.pem"};
  CommandResult echo = Echo(server, tls);
  EXPECT_EQ(echo.exit_code, 0) << echo.err << server.Log();
  EXPECT_TRUE(
      WaitUntil([&] { return server.Refused("request_deadline") >= 1; }, 30))
      << server.Log();
  // The worker is free again: the socket was shut down under DCMTK.
  EXPECT_FALSE(raw::ReadPdu(stalled, 5).has_value());
  ::close(stalled);
  EXPECT_EQ(Echo(server, tls).exit_code, 0);
}

// Segmentations in the PACS loop: a series no rule takes is held
// in the spool; a DICOM SEG drawn on it, sent afterwards (or before it),
// makes a fill job by the `fill` rule whose artifacts equal
// `interslice fill` on the same files with the same options.
class DicomFillTest : public ::testing::Test {
 protected:
  // A 16-slice series and a binary SEG drawn on it (`interslice run --seg`
  // on a region of tests/data/ct-thick), and the in-process fill of it.
  void SetUp() override {
    const std::string small = std::string(::interslice::testing::SourceDir()) +
                              "/tests/data/ct-thick";
    CommandResult run =
        RunCommand({kCli, "run", small, "--threshold", "300", "--roi",
                    "200,40,0,296,136,4", "--method", "direct", "--factor", "5",
                    "--seg", "--volume", "nrrd", "--mesh", "none", "--quiet",
                    "--out", dir_ / "run"},
                   300);
    ASSERT_EQ(run.exit_code, 0) << run.err;
    for (const auto& e :
         fs::directory_iterator(dir_ / "run/series-intensity")) {
      series_.push_back(e.path().string());
    }
    std::sort(series_.begin(), series_.end());
    ASSERT_EQ(series_.size(), 16u);
    seg_ = dir_ / "run/seg.dcm";
    // They stand for a scanner's series and a person's SEG: the node takes
    // its own results only when a rule asks (issue 39).
    for (const std::string& file : series_) {
      ASSERT_TRUE(MarkAsMadeElsewhere(file).ok()) << file;
    }
    ASSERT_TRUE(MarkAsMadeElsewhere(seg_).ok());
    CommandResult local = RunCommand(
        {kCli, "fill", seg_, "--reference", dir_ / "run/series-intensity",
         "--key-slices", "0-15:5", "--method", "direct", "--volume", "nrrd",
         "--mesh", "stl", "--threads", "1", "--quiet", "--out", dir_ / "local"},
        300);
    ASSERT_EQ(local.exit_code, 0) << local.err;
  }

  std::string WriteFillRules() {
    const std::string path = dir_ / "fill-rules.yaml";
    WriteFile(path,
              "stable_seconds: 1\n"
              "rules:\n"
              "  - name: mr-only\n"
              "    match: {modality: MR}\n"
              "    job: {threshold: 1}\n"
              "  - name: fill-seg\n"
              "    match: {modality: SEG}\n"
              "    fill: {key_slices: [0, 5, 10, 15], method: direct, "
              "volume: [nrrd], mesh: [stl]}\n");
    return path;
  }

  // Waits for the one job, checks it succeeded and that its artifacts are
  // the in-process fill's.
  void ExpectFillJob(const DicomServer& server) {
    std::vector<std::string> jobs;
    ASSERT_TRUE(WaitUntil(
        [&] {
          jobs = server.Jobs();
          return !jobs.empty();
        },
        120))
        << server.Log();
    ASSERT_EQ(jobs.size(), 1u);
    CommandResult watch = RunCommand(
        Cat({kCli, "watch", jobs[0], "--quiet"}, server.Client()), 300);
    ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
    CommandResult fetch =
        RunCommand(Cat({kCli, "fetch", jobs[0], "--out", dir_ / "remote"},
                       server.Client()),
                   120);
    ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
    ExpectSameFiles(dir_ / "local", dir_ / "remote", 2);  // labels, label-1.stl
    EXPECT_THAT(server.Log(), HasSubstr("(fill) made by rule fill-seg"));
    EXPECT_THAT(
        ReadFileOrEmpty(server.spool() + "/jobs/" + jobs[0] + "/job.pb"),
        HasSubstr("dicom:STORESCU->INTERSLICE rule fill-seg"));
    // The SEG was not left waiting.
    EXPECT_EQ(server.PendingInstances(), 0);
  }

  TempDir dir_;
  std::vector<std::string> series_;
  std::string seg_;
};

TEST_F(DicomFillTest, SegAfterItsSeriesMakesTheFillJob) {
  DicomServer server(
      dir_, "spool",
      {"--dicom-peers", WritePeers(dir_), "--rules", WriteFillRules()});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult store = StoreScu(server, {}, series_);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  // No rule takes the CT series: it is held (unmatched) for the retention.
  ASSERT_TRUE(WaitUntil([&] { return server.PendingInstances() == 0; }, 120));
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("no rule of rule set") != std::string::npos;
      },
      120))
      << server.Log();
  EXPECT_TRUE(server.Jobs().empty());
  // -R: propose only the SEG's own SOP class (storescu's default list
  // has no SEG).
  store = StoreScu(server, {"-R"}, {seg_});
  ASSERT_EQ(store.exit_code, 0) << store.err << server.Log();
  ExpectFillJob(server);
}

TEST_F(DicomFillTest, SegBeforeItsSeriesWaitsForIt) {
  DicomServer server(
      dir_, "spool",
      {"--dicom-peers", WritePeers(dir_), "--rules", WriteFillRules()});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult store = StoreScu(server, {"-R"}, {seg_});
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("waits for the series it references") !=
               std::string::npos;
      },
      120))
      << server.Log();
  EXPECT_TRUE(server.Jobs().empty());
  store = StoreScu(server, {}, series_);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ExpectFillJob(server);
}

// With fill rules, a series whose own job was made is held too: a SEG drawn
// on it still makes its fill job.
TEST_F(DicomFillTest, SeriesTakenByAJobRuleIsStillHeldForItsSeg) {
  const std::string rules = dir_ / "both-rules.yaml";
  WriteFile(rules,
            "stable_seconds: 1\n"
            "rules:\n"
            "  - name: ct\n"
            "    match: {modality: CT}\n"
            "    job: {threshold: 300, mesh: none, volume: [nii]}\n"
            "  - name: fill-seg\n"
            "    match: {modality: SEG}\n"
            "    fill: {key_slices: [0, 5, 10, 15], method: direct, "
            "volume: [nrrd], mesh: [stl]}\n");
  DicomServer server(dir_, "spool",
                     {"--dicom-peers", WritePeers(dir_), "--rules", rules});
  ASSERT_TRUE(server.up()) << server.Log();
  CommandResult store = StoreScu(server, {}, series_);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  ASSERT_TRUE(WaitUntil([&] { return server.Jobs().size() == 1; }, 120))
      << server.Log();
  store = StoreScu(server, {"-R"}, {seg_});
  ASSERT_EQ(store.exit_code, 0) << store.err << server.Log();
  std::vector<std::string> jobs;
  ASSERT_TRUE(WaitUntil(
      [&] {
        jobs = server.Jobs();
        return jobs.size() == 2;
      },
      120))
      << server.Log();
  for (const std::string& id : jobs) {
    CommandResult watch =
        RunCommand(Cat({kCli, "watch", id, "--quiet"}, server.Client()), 300);
    EXPECT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  }
  EXPECT_THAT(server.Log(), HasSubstr("(fill) made by rule fill-seg"));
  EXPECT_THAT(server.Log(), HasSubstr("made by rule ct "));
}

// ---- Issue 25: a node that explains itself ------------------------------

const std::string kServer = ::interslice::testing::ServerPath();
const std::string kStoreScp = "/usr/bin/storescp";

// storescp answering C-ECHO as `ae` on a free port (a live peer); stopped
// with the object.
class LivePeer {
 public:
  LivePeer(const TempDir& dir, const std::string& ae) : port_(FreeTcpPort()) {
    fs::create_directories(dir / "storescp-out");
    pid_ = StartProcess({kStoreScp, "-aet", ae, "-od", dir / "storescp-out",
                         std::to_string(port_)},
                        dir / "storescp.log");
    ready_ = WaitUntil(
        [&] {
          return RunCommand(
                     {kEchoScu, "-aec", ae, "127.0.0.1", std::to_string(port_)},
                     30)
                     .exit_code == 0;
        },
        60);
  }
  ~LivePeer() { StopProcess(pid_, 10); }
  bool ready() const { return ready_; }
  int port() const { return port_; }

 private:
  int port_;
  pid_t pid_;
  bool ready_ = false;
};

// Peers: a live storescp, and a port nobody listens on.
std::string WriteLiveAndDeadPeers(const TempDir& dir, int live_port,
                                  int dead_port) {
  const std::string path = dir / "peers-live-dead.yaml";
  WriteFile(path, absl::StrCat(
                      "peers:\n"
                      "  - {name: tools, ae_title: STORESCU, host: 127.0.0.1, "
                      "port: ",
                      live_port,
                      "}\n"
                      "  - {name: live, ae_title: LIVE, host: 127.0.0.1, "
                      "port: ",
                      live_port,
                      "}\n"
                      "  - {name: dead, ae_title: DEAD, host: 127.0.0.1, "
                      "port: ",
                      dead_port, "}\n"));
  return path;
}

std::vector<std::string> ProblemLines(const std::string& err) {
  std::vector<std::string> problems;
  for (absl::string_view line : absl::StrSplit(err, '\n')) {
    if (absl::StartsWith(line, "interslice-server: problem: ")) {
      problems.emplace_back(line);
    }
  }
  return problems;
}

TEST(DicomNodeConfigTest, CheckConfigEchoesPeersAndPrintsTheRules) {
  TempDir dir;
  // storescu calls as STORESCU: the live peer answers as that AE title too
  // (storescp accepts any called AE title unless told otherwise).
  LivePeer live(dir, "LIVE");
  ASSERT_TRUE(live.ready()) << ReadFileOrEmpty(dir / "storescp.log");
  const int dead_port = FreeTcpPort();
  const std::string rules = dir / "rules-check.yaml";
  WriteFile(rules,
            "stable_seconds: 2\n"
            "rules:\n"
            "  - name: ct-bone\n"
            "    match: {modality: CT, called_ae: INTERSLICE, "
            "slice_count: {min: 20}}\n"
            "    job: {threshold: 300}\n"
            "    send_to: [live]\n"
            "  - name: seg\n"
            "    match: {modality: SEG}\n"
            "    fill: {}\n");
  auto check = [&](const std::string& peers, const std::string& rules_file) {
    return RunCommand(
        {kServer, "--check-config", "--spool", dir / "spool", "--dicom-listen",
         "127.0.0.1:0", "--dicom-ae", "INTERSLICE", "--dicom-peers", peers,
         "--rules", rules_file},
        120);
  };
  CommandResult r =
      check(WriteLiveAndDeadPeers(dir, live.port(), dead_port), rules);
  EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
  EXPECT_THAT(r.out,
              HasSubstr("rule 'ct-bone' (#1): a series with modality CT, "
                        "called_ae INTERSLICE, slice_count >= 20 -> job, "
                        "send_to live"));
  EXPECT_THAT(r.out, HasSubstr("rule 'seg' (#2): a segmentation (SEG, "
                               "RTSTRUCT) with modality SEG -> fill job"));
  EXPECT_THAT(r.out,
              HasSubstr(absl::StrCat("peer live (LIVE@127.0.0.1:", live.port(),
                                     "): C-ECHO answered")));
  // One line for the one problem: the dead peer, named.
  std::vector<std::string> problems = ProblemLines(r.err);
  ASSERT_EQ(problems.size(), 1u) << r.err;
  EXPECT_THAT(problems[0], HasSubstr(absl::StrCat(
                               "peer dead (DEAD@127.0.0.1:", dead_port, ")")));
  // A check starts nothing and writes nothing.
  EXPECT_FALSE(fs::exists(dir / "spool"));

  // Only live peers: exit code 0.
  const std::string good = dir / "peers-good.yaml";
  WriteFile(good, absl::StrCat("peers:\n  - {name: live, ae_title: LIVE, "
                               "host: 127.0.0.1, port: ",
                               live.port(), "}\n"));
  r = check(good, rules);
  EXPECT_EQ(r.exit_code, 0) << r.out << r.err;
  EXPECT_THAT(r.out, HasSubstr("configuration OK"));
  EXPECT_TRUE(ProblemLines(r.err).empty()) << r.err;

  // A rule for an AE title the server does not listen as: the problem line
  // says which rule and which titles it does listen as.
  const std::string bad = dir / "rules-bad.yaml";
  WriteFile(bad,
            "rules:\n  - name: three-d\n    match: {called_ae: INTERSLICE_3D}\n"
            "    job: {threshold: 300}\n");
  r = check(good, bad);
  EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
  problems = ProblemLines(r.err);
  ASSERT_EQ(problems.size(), 1u) << r.err;
  EXPECT_THAT(problems[0],
              HasSubstr("rule 'three-d' (#1): match.called_ae: INTERSLICE_3D "
                        "is not an AE title this server listens as "
                        "(--dicom-ae INTERSLICE)"));

  // A peer pulled from by C-MOVE needs the listener as its destination: the
  // start refuses that, and so does the check (which echoes the peer all the
  // same).
  const std::string move = dir / "peers-move.yaml";
  WriteFile(move, absl::StrCat("peers:\n  - {name: live, ae_title: LIVE, "
                               "host: 127.0.0.1, port: ",
                               live.port(), ", retrieve: move}\n"));
  r = RunCommand({kServer, "--check-config", "--spool", dir / "spool",
                  "--dicom-peers", move},
                 120);
  EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
  problems = ProblemLines(r.err);
  ASSERT_EQ(problems.size(), 1u) << r.err;
  EXPECT_THAT(problems[0],
              HasSubstr("peer 'live' has retrieve: move, which needs the "
                        "DICOM listener (--dicom-listen)"));
  EXPECT_THAT(r.out, HasSubstr("C-ECHO answered"));
}

TEST(DicomNodeConfigTest, UnreachablePeerIsAWarningAndAMetricAtStart) {
  TempDir dir;
  LivePeer live(dir, "LIVE");
  ASSERT_TRUE(live.ready()) << ReadFileOrEmpty(dir / "storescp.log");
  const int dead_port = FreeTcpPort();
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", WriteLiveAndDeadPeers(dir, live.port(), dead_port),
       "--rules", WriteRules(dir, 1, false)});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::string reachable = "interslice_dicom_peer_reachable{peer=\"";
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Metric(reachable + "live\"}") >= 0 &&
               server.Metric(reachable + "dead\"}") >= 0;
      },
      120))
      << server.Log();
  EXPECT_EQ(server.Metric(reachable + "live\"}"), 1);
  EXPECT_EQ(server.Metric(reachable + "dead\"}"), 0);
  const std::string log = server.Log();
  EXPECT_THAT(log,
              HasSubstr(absl::StrCat("peer dead (DEAD@127.0.0.1:", dead_port,
                                     ") did not answer a C-ECHO at "
                                     "start-up")));
  EXPECT_THAT(log, HasSubstr(absl::StrCat("peer live (LIVE@127.0.0.1:",
                                          live.port(), ") answered a C-ECHO")));
  // The server serves anyway.
  CommandResult echo = RunCommand({kEchoScu, "-aet", "STORESCU", "-aec",
                                   "INTERSLICE", "127.0.0.1", server.port()});
  EXPECT_EQ(echo.exit_code, 0) << echo.err;
}

// A series no rule takes: one log line naming each rule and the first
// criterion that failed, with no UID or patient data.
TEST(DicomNodeConfigTest, UnmatchedSeriesLogSaysWhichCriterionFailed) {
  TempDir dir;
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules",
                      WriteRules(dir, 0.5, true)});
  ASSERT_TRUE(server.up()) << server.Log();
  // 5 slices of the phantom: fewer than ct-head's slice_count min 20.
  std::vector<std::string> files = PhantomFiles();
  files.resize(5);
  CommandResult store = StoreScu(server, {}, files);
  ASSERT_EQ(store.exit_code, 0) << store.err;
  std::string line;
  ASSERT_TRUE(WaitUntil(
      [&] {
        for (absl::string_view l : absl::StrSplit(server.Log(), '\n')) {
          if (absl::StrContains(l, "no rule of rule set")) {
            line = std::string(l);
            return true;
          }
        }
        return false;
      },
      120))
      << server.Log();
  EXPECT_THAT(line, HasSubstr("rule 'not-mr': modality is 'CT', not 'MR'; "
                              "rule 'ct-head': slice_count 5 not >= 20"));
  EXPECT_THAT(line, ::testing::Not(HasSubstr("1.3.46.670589")));
  EXPECT_TRUE(server.Jobs().empty());
}

// SIGHUP reloads the peers and rules files: a bad file keeps the old
// configuration and says why; a good one becomes the next generation, for
// series completed and associations requested from then on.
TEST(DicomNodeConfigTest, SighupReloadsPeersAndRulesAndRefusesABadFile) {
  TempDir dir;
  const std::string peers = WritePeers(dir);
  const std::string rules = dir / "rules-reload.yaml";
  WriteFile(
      rules,
      "stable_seconds: 0.5\nrules:\n"
      "  - {name: mr-only, match: {modality: MR}, job: {threshold: 1}}\n");
  const std::string audit = dir / "audit.jsonl";
  DicomServer server(
      dir, "spool",
      {"--dicom-peers", peers, "--rules", rules, "--audit-log", audit});
  ASSERT_TRUE(server.up()) << server.Log();
  const std::string generation = "interslice_dicom_config_generation";
  EXPECT_EQ(server.Metric(generation), 1);
  auto log_has = [&](const std::string& text) {
    return WaitUntil([&] { return absl::StrContains(server.Log(), text); },
                     120);
  };
  auto hangup = [&] { ASSERT_EQ(::kill(server.pid(), SIGHUP), 0); };
  std::vector<std::string> files = PhantomFiles();
  files.resize(5);
  // Generation 1: the CT series matches nothing.
  ASSERT_EQ(StoreScu(server, {}, files).exit_code, 0);
  ASSERT_TRUE(log_has("rule 'mr-only': modality is 'CT', not 'MR'"))
      << server.Log();
  // NEWCOMER is not a peer yet.
  auto newcomer_echo = [&] {
    return RunCommand({kEchoScu, "-aet", "NEWCOMER", "-aec", "INTERSLICE",
                       "127.0.0.1", server.port()})
        .exit_code;
  };
  EXPECT_NE(newcomer_echo(), 0);

  // A bad rules file: refused, generation 1 stays, the log says why.
  WriteFile(rules,
            "rules:\n  - {name: x, match: {modality: CT}, job: "
            "{threshold: 300, methd: direct}}\n");
  hangup();
  ASSERT_TRUE(log_has("reload refused, configuration generation 1 stays live"))
      << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("methd"));
  EXPECT_EQ(server.Metric(generation), 1);
  // A rule that sends to a peer added in the same reload: the peers are
  // reloaded with the rules (server/node/peer_registry.h), so it is taken.
  // (Until the peer registry, the outbox held the peers of the start and
  // such a reload was refused.)
  WriteFile(peers + ".new",
            ReadFileOrEmpty(peers) +
                "  - {name: brandnew, ae_title: NEW, host: 127.0.0.1, "
                "port: 2}\n");
  fs::rename(peers + ".new", peers);
  WriteFile(rules,
            "rules:\n  - {name: x, match: {modality: MR}, job: "
            "{threshold: 300}, send_to: [brandnew]}\n");
  hangup();
  ASSERT_TRUE(log_has("configuration generation 2 is live")) << server.Log();
  EXPECT_EQ(server.Metric(generation), 2);

  // Good files: generation 2, with the new caller and the new rule.
  WriteFile(peers,
            "peers:\n"
            "  - {name: tools, ae_title: STORESCU, host: 127.0.0.1, port: 1}\n"
            "  - {name: newcomer, ae_title: NEWCOMER, host: 127.0.0.1, "
            "port: 1}\n");
  WriteFile(rules,
            "stable_seconds: 0.5\nrules:\n"
            "  - name: ct-any\n"
            "    match: {modality: CT}\n"
            "    job: {threshold: 300, roi: [208, 208, 0, 304, 304, 5], "
            "mesh: none, volume: [nii], previews: none}\n");
  hangup();
  ASSERT_TRUE(log_has("configuration generation 3 is live")) << server.Log();
  EXPECT_EQ(server.Metric(generation), 3);
  EXPECT_EQ(newcomer_echo(), 0) << server.Log();
  ASSERT_EQ(StoreScu(server, {}, files).exit_code, 0);
  ASSERT_TRUE(log_has("made by rule ct-any")) << server.Log();
  EXPECT_EQ(server.Jobs().size(), 1u);
  // Each reload, refused or not, is in the audit trail (docs/audit.md).
  const std::string trail = ReadFileOrEmpty(audit);
  EXPECT_THAT(trail, HasSubstr("\"event\":\"config.reloaded\",\"atna\":"
                               "\"110100 Application Activity\",\"outcome\":"
                               "\"success\",\"count\":2"))
      << trail;
  EXPECT_THAT(trail, HasSubstr("reload refused, generation 1 stays live"))
      << trail;
}

// Issue 25: a series no rule matched is kept; once the rules file is fixed
// and reloaded (SIGHUP), `interslice kept rerun` makes its job, whose
// results equal `interslice run`'s on the same files with the same options.
// Admins only; an unknown id is NOT_FOUND.
TEST(DicomNodeConfigTest, KeptSeriesRunAgainAfterTheRulesAreFixed) {
  TempDir dir;
  CommandResult local =
      RunCommand(Cat(Cat({kCli, "run", kPhantom}, kJobArgs),
                     {"--out", dir / "local", "--quiet", "--threads", "1"}),
                 300);
  ASSERT_EQ(local.exit_code, 0) << local.err;
  const std::string rules = dir / "rules-kept.yaml";
  auto write_rules = [&](int min_slices) {
    WriteFile(rules, absl::StrCat("stable_seconds: 0.5\nrules:\n"
                                  "  - name: ct-head\n"
                                  "    match: {modality: CT, slice_count: "
                                  "{min: ",
                                  min_slices, "}}\n    job: ", kJobYaml, "\n"));
  };
  write_rules(40);  // the mistake: the phantom has 28 slices
  DicomServer server(dir, "spool",
                     {"--dicom-peers", WritePeers(dir), "--rules", rules},
                     {.extra_tokens = "user:user-token\n"});
  ASSERT_TRUE(server.up()) << server.Log();
  std::ofstream(dir / "user.token") << "user-token\n";
  const std::vector<std::string> user =
      Cat(Cat({"--server"}, {server.Client()[1]}),
          {"--token-file", dir / "user.token"});
  const std::vector<std::string> files = PhantomFiles();
  ASSERT_EQ(StoreScu(server, {}, files).exit_code, 0);
  ASSERT_TRUE(WaitUntil(
      [&] { return absl::StrContains(server.Log(), "no rule of rule set"); },
      120))
      << server.Log();

  // Listed, one line, with why.
  CommandResult list =
      RunCommand(Cat({kCli, "kept", "list"}, server.Client()), 60);
  ASSERT_EQ(list.exit_code, 0) << list.err;
  std::vector<std::string> lines =
      absl::StrSplit(list.out, '\n', absl::SkipEmpty());
  ASSERT_EQ(lines.size(), 1u) << list.out;
  EXPECT_THAT(lines[0], HasSubstr("  STORESCU -> INTERSLICE  CT  28 "
                                  "instance(s)  study "));
  EXPECT_THAT(lines[0], HasSubstr("no rule matched; the rules now: rule "
                                  "'ct-head': slice_count 28 not >= 40"));
  DcmFileFormat first;
  ASSERT_TRUE(first.loadFile(OFFilename(files[0].c_str())).good());
  OFString study, series;
  first.getDataset()->findAndGetOFString(DCM_StudyInstanceUID, study);
  first.getDataset()->findAndGetOFString(DCM_SeriesInstanceUID, series);
  EXPECT_THAT(lines[0], HasSubstr(absl::StrCat("study ", study.c_str(),
                                               "  series ", series.c_str())));
  const std::string id = lines[0].substr(0, lines[0].find(' '));

  // Not for other identities.
  for (const std::vector<std::string>& command :
       {std::vector<std::string>{kCli, "kept", "list"},
        std::vector<std::string>{kCli, "kept", "rerun", id}}) {
    CommandResult refused = RunCommand(Cat(command, user), 60);
    EXPECT_EQ(refused.exit_code, 1);
    EXPECT_THAT(refused.err, HasSubstr("admin identities only"));
    EXPECT_EQ(std::count(refused.err.begin(), refused.err.end(), '\n'), 1);
  }
  // An unknown id.
  CommandResult unknown = RunCommand(
      Cat({kCli, "kept", "rerun", "0123456789abcdef0123456789abcdef-1"},
          server.Client()),
      60);
  EXPECT_EQ(unknown.exit_code, 1);
  EXPECT_THAT(unknown.err, HasSubstr("no kept series has that id"));
  // The rules unchanged: not matched, not an error.
  CommandResult still =
      RunCommand(Cat({kCli, "kept", "rerun", id}, server.Client()), 60);
  ASSERT_EQ(still.exit_code, 0) << still.err;
  EXPECT_EQ(still.out,
            absl::StrCat("not matched ", id,
                         ": no rule matched: rule 'ct-head': slice_count 28 "
                         "not >= 40\n"));
  EXPECT_TRUE(server.Jobs().empty());

  // The rules fixed and reloaded.
  write_rules(20);
  ASSERT_EQ(::kill(server.pid(), SIGHUP), 0);
  ASSERT_TRUE(WaitUntil(
      [&] {
        return absl::StrContains(server.Log(),
                                 "configuration generation 2 is live");
      },
      120))
      << server.Log();
  CommandResult rerun =
      RunCommand(Cat({kCli, "kept", "rerun", id}, server.Client()), 120);
  ASSERT_EQ(rerun.exit_code, 0) << rerun.err << server.Log();
  ASSERT_TRUE(absl::StartsWith(rerun.out, "job ")) << rerun.out;
  const std::string job =
      std::string(absl::StripAsciiWhitespace(rerun.out.substr(4)));
  EXPECT_EQ(server.Jobs(), std::vector<std::string>{job});
  CommandResult watch =
      RunCommand(Cat({kCli, "watch", job, "--quiet"}, server.Client()), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  CommandResult fetch = RunCommand(
      Cat({kCli, "fetch", job, "--out", dir / "remote"}, server.Client()), 120);
  ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
  ExpectSameFiles(dir / "local", dir / "remote", 12, {},
                  DicomComparison::kSameSize);
  // The job is the rule's, as if the series had just completed.
  CommandResult jobs =
      RunCommand(Cat({kCli, "list", "--all"}, server.Client()), 60);
  EXPECT_THAT(jobs.out,
              HasSubstr("origin    DICOM from STORESCU to INTERSLICE, rule "
                        "ct-head\n"));
  // Kept again, now with its job.
  list = RunCommand(Cat({kCli, "kept", "list"}, server.Client()), 60);
  ASSERT_EQ(list.exit_code, 0) << list.err;
  EXPECT_THAT(list.out, HasSubstr(absl::StrCat("job ", job, " made\n")));
  // Nothing to run without a job any more.
  CommandResult all = RunCommand(
      Cat({kCli, "kept", "rerun", "--all-unmatched"}, server.Client()), 60);
  EXPECT_EQ(all.exit_code, 0) << all.err;
  EXPECT_EQ(all.out, "");
  // Neither an id nor --all-unmatched: one line, exit 1.
  CommandResult neither =
      RunCommand(Cat({kCli, "kept", "rerun"}, server.Client()), 60);
  EXPECT_EQ(neither.exit_code, 1);
  EXPECT_THAT(neither.err, HasSubstr("give a kept series' id or "
                                     "--all-unmatched"));
  EXPECT_THAT(server.Log(), ::testing::Not(HasSubstr("1.3.46.670589")));
}

}  // namespace
}  // namespace interslice::testing
