// End-to-end tests of the DICOM listener: real interslice-server processes on
// loopback (ports from --port-file), driven by DCMTK's own tools (echoscu,
// storescu) and by the `interslice` client.
#include <arpa/inet.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "tests/server/process.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kCli = INTERSLICE_CLI_PATH;
// DCMTK's tools (Debian package dcmtk, in install-deps.sh).
const std::string kEchoScu = "/usr/bin/echoscu";
const std::string kStoreScu = "/usr/bin/storescu";
const std::string kServer = INTERSLICE_SERVER_PATH;
const std::string kPhantom =
    std::string(INTERSLICE_SOURCE_DIR) + "/data/ct-head-phantom-thick";
// A small job on the phantom: a 96 x 96 region of all 28 slices.
const char kJobYaml[] =
    "{threshold: 300, roi: [208, 208, 0, 304, 304, 28], mesh: [stl], "
    "volume: [nii], previews: [png, dicom]}";
const std::vector<std::string> kJobArgs = {
    "--threshold", "300",      "--roi", "208,208,0,304,304,28", "--mesh",
    "stl",         "--volume", "nii",   "--previews",           "png,dicom"};

std::vector<std::string> Cat(std::vector<std::string> a,
                             const std::vector<std::string>& b) {
  a.insert(a.end(), b.begin(), b.end());
  return a;
}

std::vector<std::string> PhantomFiles() {
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(kPhantom)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  return files;
}

class TempDir {
 public:
  TempDir() {
    char name[] = "/tmp/interslice-dicom-test-XXXXXX";
    path_ = mkdtemp(name);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string operator/(const std::string& name) const {
    return (fs::path(path_) / name).string();
  }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

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

class DicomServer {
 public:
  DicomServer(const TempDir& dir, const std::string& name,
              std::vector<std::string> extra)
      : spool_(dir / name), log_(dir / (name + ".log")) {
    const std::string port_file = spool_ + ".port";
    std::error_code ec;
    fs::remove(port_file, ec);  // a restart must not read the old ports
    std::ofstream(dir / "admin.tokens") << "admin:admin-token\n";
    std::ofstream(dir / "admin.token") << "admin-token\n";
    token_file_ = dir / "admin.token";
    std::vector<std::string> argv = {kServer,
                                     "--listen",
                                     "127.0.0.1:0",
                                     "--spool",
                                     spool_,
                                     "--port-file",
                                     port_file,
                                     "--workers",
                                     "1",
                                     "--threads-per-job",
                                     "1",
                                     "--drain-grace",
                                     "0",
                                     "--auth-token-file",
                                     dir / "admin.tokens",
                                     "--admin-identity",
                                     "admin",
                                     "--dicom-listen",
                                     "0.0.0.0:0",
                                     "--dicom-acse-timeout",
                                     "3"};
    pid_ = StartProcess(Cat(argv, extra), log_);
    for (int i = 0; i < 1000; ++i) {
      const int rc = WaitProcess(pid_, 0);
      if (rc != -1) {  // ended at start-up (reaped here)
        exit_code_ = rc;
        pid_ = -1;
        break;
      }
      std::ifstream in(port_file);
      int grpc = 0, metrics = 0, dicom = 0;
      if (in >> grpc >> metrics >> dicom) {
        grpc_port_ = grpc;
        dicom_port_ = dicom;
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }
  ~DicomServer() {
    if (pid_ > 0) {
      kill(pid_, SIGTERM);
      const int rc = WaitProcess(pid_, 60);
      EXPECT_EQ(rc, 0) << "interslice-server did not exit cleanly\n" << Log();
      if (rc == -1) {
        kill(pid_, SIGKILL);
        waitpid(pid_, nullptr, 0);
      }
    }
  }
  // The exit code if the server ended (e.g. a bad configuration), else -1.
  int ExitCode(double wait_seconds) {
    if (pid_ < 0) return exit_code_;
    const int rc = WaitProcess(pid_, wait_seconds);
    if (rc != -1) pid_ = -1;
    return rc;
  }
  bool up() const { return dicom_port_ > 0; }
  std::string port() const { return std::to_string(dicom_port_); }
  std::vector<std::string> Client() const {
    return {"--server", absl::StrCat("127.0.0.1:", grpc_port_), "--token-file",
            token_file_};
  }
  std::string Log() const { return ReadFileOrEmpty(log_); }
  const std::string& spool() const { return spool_; }

  // Instances waiting in series folders.
  int PendingInstances() const {
    int n = 0;
    std::error_code ec;
    for (const auto& e : fs::recursive_directory_iterator(
             fs::path(spool_) / "dicom-in" / "series", ec)) {
      if (e.path().extension() == ".dcm") ++n;
    }
    return n;
  }

  // Job ids the server lists (admin view).
  std::vector<std::string> Jobs() const {
    CommandResult list = RunCommand(Cat({kCli, "list", "--all"}, Client()), 60);
    std::vector<std::string> ids;
    for (absl::string_view line : absl::StrSplit(list.out, '\n')) {
      std::vector<std::string> words =
          absl::StrSplit(line, ' ', absl::SkipEmpty());
      if (!words.empty()) ids.push_back(words[0]);
    }
    return ids;
  }

 private:
  std::string spool_, log_, token_file_;
  pid_t pid_ = -1;
  int exit_code_ = -1;
  int grpc_port_ = 0, dicom_port_ = 0;
};

bool WaitUntil(const std::function<bool()>& done, double seconds) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int>(seconds * 1000));
  while (std::chrono::steady_clock::now() < end) {
    if (done()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return done();
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
  EXPECT_THAT(server.Log(), HasSubstr("STRANGER rejected"));
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
      60))
      << server.Log();
  ASSERT_EQ(jobs.size(), 1u);
  CommandResult watch = RunCommand(
      Cat({kCli, "watch", jobs[0], "--quiet"}, server.Client()), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  CommandResult fetch = RunCommand(
      Cat({kCli, "fetch", jobs[0], "--out", dir / "remote"}, server.Client()),
      120);
  ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
  // Every file, the previews' included: the same bytes (DICOM files: the
  // same size; their creation times differ).
  int compared = 0;
  for (const auto& e : fs::recursive_directory_iterator(dir / "local")) {
    if (!e.is_regular_file()) continue;
    const std::string name = fs::relative(e.path(), dir / "local").string();
    const std::string remote = dir / ("remote/" + name);
    ASSERT_TRUE(fs::exists(remote)) << name;
    if (e.path().extension() == ".dcm") {
      EXPECT_EQ(fs::file_size(e.path()), fs::file_size(remote)) << name;
    } else {
      EXPECT_TRUE(ReadFileOrEmpty(e.path().string()) == ReadFileOrEmpty(remote))
          << name << " differs";
    }
    ++compared;
  }
  // distance, mask, surface, its note, 4 PNG and 4 DICOM previews.
  EXPECT_GE(compared, 12);
  EXPECT_TRUE(fs::exists(dir / "remote/previews-dicom/IM00004.dcm"));
  const std::string log = server.Log();
  EXPECT_THAT(log, HasSubstr("made by rule ct-head"));
  EXPECT_THAT(log, HasSubstr("STORESCU -> INTERSLICE released: 28 instance(s) "
                             "kept, 0 refused"));
  // The job records where it came from (JobStatus.origin).
  EXPECT_THAT(ReadFileOrEmpty(server.spool() + "/jobs/" + jobs[0] + "/job.pb"),
              HasSubstr("dicom:STORESCU->INTERSLICE rule ct-head"));
  // Nothing was left behind in the DICOM spool.
  EXPECT_EQ(server.PendingInstances(), 0);
  // No UID of the phantom reaches the log.
  EXPECT_THAT(log, ::testing::Not(HasSubstr("1.3.46.670589")));
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
      30))
      << server.Log();
  std::this_thread::sleep_for(std::chrono::seconds(1));
  EXPECT_EQ(server.PendingInstances(), 28);
  EXPECT_TRUE(server.Jobs().empty());
  // The same series again, released: complete at once (not after 600 s),
  // the re-sent instances replace themselves.
  CommandResult released = StoreScu(server, {}, files);
  EXPECT_EQ(released.exit_code, 0) << released.err;
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 30))
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
  ASSERT_TRUE(WaitUntil([&] { return !again.Jobs().empty(); }, 60))
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
  ASSERT_TRUE(WaitUntil([&] { return !server.Jobs().empty(); }, 30))
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
  EXPECT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("aborted: an instance passed 100000 bytes") !=
               std::string::npos;
      },
      10))
      << server.Log();
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
      "set -e; cd ", dir.path(), "; exec >openssl.log 2>&1\n",
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
      std::string(INTERSLICE_SOURCE_DIR) + "/docs/examples";
  DicomServer server(dir, "spool",
                     {"--dicom-peers", examples + "/peers.yaml", "--rules",
                      examples + "/rules.yaml", "--dicom-ae", "INTERSLICE",
                      "--dicom-ae", "INTERSLICE_3D"});
  ASSERT_TRUE(server.up()) << server.Log();
}

// Segmentations in the PACS loop (issue 13): a series no rule takes is held
// in the spool; a DICOM SEG drawn on it, sent afterwards (or before it),
// makes a fill job by the `fill` rule whose artifacts equal
// `interslice fill` on the same files with the same options.
class DicomFillTest : public ::testing::Test {
 protected:
  // A 16-slice series and a binary SEG drawn on it (`interslice run --seg`
  // on a region of tests/data/ct-thick), and the in-process fill of it.
  void SetUp() override {
    const std::string small =
        std::string(INTERSLICE_SOURCE_DIR) + "/tests/data/ct-thick";
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
        60))
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
    int compared = 0;
    for (const auto& e : fs::directory_iterator(dir_ / "local")) {
      const std::string name = e.path().filename().string();
      ASSERT_TRUE(fs::exists(fs::path(dir_ / "remote") / name)) << name;
      EXPECT_TRUE(ReadFileOrEmpty(e.path().string()) ==
                  ReadFileOrEmpty(dir_ / ("remote/" + name)))
          << name << " differs";
      ++compared;
    }
    EXPECT_GE(compared, 2);  // labels.nrrd, label-1.stl
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
  ASSERT_TRUE(WaitUntil([&] { return server.PendingInstances() == 0; }, 30));
  ASSERT_TRUE(WaitUntil(
      [&] {
        return server.Log().find("no rule of rule set") != std::string::npos;
      },
      30))
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
      30))
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
  ASSERT_TRUE(WaitUntil([&] { return server.Jobs().size() == 1; }, 60))
      << server.Log();
  store = StoreScu(server, {"-R"}, {seg_});
  ASSERT_EQ(store.exit_code, 0) << store.err << server.Log();
  std::vector<std::string> jobs;
  ASSERT_TRUE(WaitUntil(
      [&] {
        jobs = server.Jobs();
        return jobs.size() == 2;
      },
      60))
      << server.Log();
  for (const std::string& id : jobs) {
    CommandResult watch =
        RunCommand(Cat({kCli, "watch", id, "--quiet"}, server.Client()), 300);
    EXPECT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  }
  EXPECT_THAT(server.Log(), HasSubstr("(fill) made by rule fill-seg"));
  EXPECT_THAT(server.Log(), HasSubstr("made by rule ct "));
}

}  // namespace
}  // namespace interslice::testing
