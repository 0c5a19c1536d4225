// Replicas that answer for each other (server/net/grpc/forwarding.h): three
// real interslice-server processes on loopback, each advertising its own
// address, and the real `interslice` client round-robin over all three.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <set>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "grpcpp/grpcpp.h"
#include "interslice/v1/interslice.grpc.pb.h"
#include "server/net/grpc/forwarding.h"
#include "tests/testing/files.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"

namespace interslice::testing {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kCli = ::interslice::testing::CliPath();
const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";
// Small and fast: a 96 x 96 region of the 4 slices.
const std::vector<std::string> kSmallJob = {kSeries, "--threshold", "300",
                                            "--roi", "200,200,0,296,296,4"};
const std::vector<std::string> kOutputs = {"--volume", "nii,nrrd", "--mesh",
                                           "stl,ply"};
// Runs until cancelled.
const std::vector<std::string> kLongJob = {
    kSeries,        "--threshold", "300", "--roi", "100,100,0,400,400,4",
    "--iterations", "100000000"};
constexpr int kJobs = 30;

CommandResult Cli(const std::vector<std::string>& args, double timeout = 120) {
  return RunCommand(Cat({kCli}, args), timeout);
}

std::string Trim(std::string s) {
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
  return s;
}

// A replica in `dir`: a fixed loopback port taken before it starts (it
// advertises its address to the others, and keeps it across a restart),
// one worker on one thread. Not started.
std::unique_ptr<ServerProcess> Replica(const std::string& dir,
                                       std::vector<std::string> extra = {},
                                       const std::string& tls_ca_file = "") {
  const std::string address = absl::StrCat("127.0.0.1:", FreeTcpPort());
  return std::make_unique<ServerProcess>(
      ServerOptions{.spool = dir + "/spool",
                    .log = dir + "/server.log",
                    .listen = address,
                    .extra = Cat({"--advertise", address}, extra),
                    .threads_per_job = 1,
                    .tls_ca_file = tls_ca_file});
}

std::set<std::string> JobsIn(const std::string& spool) {
  std::set<std::string> ids;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(fs::path(spool) / "jobs", ec)) {
    ids.insert(e.path().filename().string());
  }
  return ids;
}

// The files of a run through the server equal the in-process run's (the
// report differs: timings).
void ExpectSameFiles(const std::string& expected_dir,
                     const std::string& actual_dir) {
  testing::ExpectSameFiles(expected_dir, actual_dir, 4, {"report.json"});
}

std::unique_ptr<v1::InterSlice::Stub> StubTo(const std::string& address) {
  return v1::InterSlice::NewStub(
      grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
}

// The first status of a Watch through `address`, or the call's error.
grpc::Status FirstStatus(const std::string& address, const std::string& id,
                         v1::JobStatus* status) {
  auto stub = StubTo(address);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(30));
  v1::WatchRequest request;
  request.set_job_id(id);
  auto reader = stub->Watch(&context, request);
  if (reader->Read(status)) context.TryCancel();
  grpc::Status s = reader->Finish();
  return s.error_code() == grpc::CANCELLED ? grpc::Status::OK : s;
}

TEST(ReplicaTest, AnyReplicaAnswersForAnyJobAndAKilledOneComesBack) {
  TempDir dir;
  CommandResult local_run = Cli(Cat(
      Cat({"run"}, kSmallJob),
      Cat(kOutputs, {"--out", dir / "local", "--quiet", "--threads", "1"})));
  ASSERT_EQ(local_run.exit_code, 0) << local_run.err;

  std::vector<std::unique_ptr<ServerProcess>> replicas;
  std::vector<std::string> addresses;
  for (int i = 0; i < 3; ++i) {
    fs::create_directories(dir / absl::StrCat("r", i));
    replicas.push_back(Replica(dir / absl::StrCat("r", i)));
    ASSERT_TRUE(replicas.back()->Start());
    addresses.push_back(replicas.back()->address());
  }
  const std::vector<std::string> balanced = {
      "--server", "ipv4:" + absl::StrJoin(addresses, ",")};
  std::map<std::string, int> owner_index;
  for (int i = 0; i < 3; ++i) owner_index[addresses[i]] = i;

  // Submits one job through the balanced channel; returns its id.
  std::vector<std::string> ids;
  std::vector<int> owners;
  auto submit = [&] {
    CommandResult r =
        Cli(Cat(Cat(Cat({"submit"}, kSmallJob), kOutputs), balanced));
    ASSERT_EQ(r.exit_code, 0) << r.err;
    const std::string id = Trim(r.out);
    std::optional<std::string> owner = server::JobOwner(id);
    ASSERT_TRUE(owner.has_value()) << id;
    ASSERT_EQ(owner_index.count(*owner), 1u) << *owner;
    ids.push_back(id);
    owners.push_back(owner_index[*owner]);
  };
  for (int i = 0; i < kJobs / 2; ++i) {
    submit();
    if (HasFatalFailure()) return;
  }
  // The balancer spread the jobs (30 picks over 3 replicas).
  EXPECT_GE(std::set<int>(owners.begin(), owners.end()).size(), 2u);

  // Cancel through a replica that does not own the job.
  CommandResult long_job =
      Cli(Cat(Cat({"submit"}, kLongJob), {"--server", addresses[2]}));
  ASSERT_EQ(long_job.exit_code, 0) << long_job.err;
  const std::string long_id = Trim(long_job.out);
  CommandResult cancel = Cli({"cancel", long_id, "--server", addresses[0]});
  EXPECT_EQ(cancel.exit_code, 0) << cancel.err;
  v1::JobStatus status;
  WaitFor(
      [&] {
        return FirstStatus(addresses[1], long_id, &status).ok() &&
               status.state() == v1::JOB_STATE_CANCELLED;
      },
      std::chrono::seconds(60));
  EXPECT_EQ(status.state(), v1::JOB_STATE_CANCELLED);

  // Replica 1 dies (SIGKILL) in the middle; the balanced channel carries on
  // with the two others.
  // (The one holding most jobs.)
  std::vector<int> held(3, 0);
  for (int o : owners) ++held[o];
  const int victim = static_cast<int>(
      std::max_element(held.begin(), held.end()) - held.begin());
  std::cerr << "jobs per replica before the kill: " << held[0] << " " << held[1]
            << " " << held[2] << "\n";
  replicas[victim]->Kill();
  for (int i = kJobs / 2; i < kJobs; ++i) {
    submit();
    if (HasFatalFailure()) return;
    EXPECT_NE(owners.back(), victim);
  }
  // A job of the dead replica, asked for at a live one: UNAVAILABLE naming
  // the owner (not "no such job").
  int dead_job = -1;
  pid_t waiting = -1;
  for (int i = 0; i < kJobs; ++i) {
    if (owners[i] == victim) dead_job = i;
  }
  if (dead_job < 0) {
    // The balancer sent nothing to the victim: the rest still holds, but
    // say so (it should not happen with 15 round-robin picks).
    ADD_FAILURE() << "no job landed on replica " << victim;
  } else {
    const grpc::Status s =
        FirstStatus(addresses[(victim + 1) % 3], ids[dead_job], &status);
    EXPECT_EQ(s.error_code(), grpc::UNAVAILABLE) << s.error_message();
    EXPECT_THAT(s.error_message(), HasSubstr(addresses[victim]));
    // The client's watch keeps retrying while the owner is down...
    waiting = StartProcess(
        {kCli, "watch", ids[dead_job], "--quiet", "--server", addresses[0]},
        dir / "waiting-watch.log");
    // A check that something does NOT happen: the watch is still waiting
    // 1.5 s later (a sleep, not a wait for a condition).
    std::this_thread::sleep_for(std::chrono::milliseconds(1500));
    EXPECT_EQ(WaitProcess(waiting, 0), -1)
        << ReadFileOrEmpty(dir / "waiting-watch.log");
  }
  // ...and the owner comes back with its spool: the waiting watch ends.
  ASSERT_TRUE(replicas[victim]->Start());
  if (waiting > 0) {
    EXPECT_EQ(WaitProcess(waiting, 60), 0)
        << ReadFileOrEmpty(dir / "waiting-watch.log");
  }

  // Every job, through the balanced channel: watched to the end, fetched,
  // and the same files as the in-process run.
  for (int i = 0; i < kJobs; ++i) {
    CommandResult watch = Cli(Cat({"watch", ids[i], "--quiet"}, balanced));
    ASSERT_EQ(watch.exit_code, 0)
        << ids[i] << ": " << watch.err << replicas[owners[i]]->Log();
    const std::string out = dir / absl::StrCat("out", i);
    CommandResult fetch = Cli(Cat({"fetch", ids[i], "--out", out}, balanced));
    ASSERT_EQ(fetch.exit_code, 0) << fetch.err;
    ExpectSameFiles(dir / "local", out);
  }

  // Nothing lost or duplicated: each spool holds exactly the jobs whose ids
  // name it.
  std::set<std::string> all(ids.begin(), ids.end());
  EXPECT_EQ(all.size(), static_cast<size_t>(kJobs));
  for (int r = 0; r < 3; ++r) {
    std::set<std::string> expected;
    for (int i = 0; i < kJobs; ++i) {
      if (owners[i] == r) expected.insert(ids[i]);
    }
    if (r == 2) expected.insert(long_id);
    EXPECT_EQ(JobsIn(replicas[r]->spool()), expected) << "replica " << r;
  }
  // Forwarded calls are not forwarded again, and forged ids naming hosts
  // outside the replica set are unknown jobs (no connection to them).
  for (const std::string& forged :
       {"0123456789abcdef" + server::JobIdSuffix("10.1.2.3:50051"),
        "0123456789abcdef" + server::JobIdSuffix("example.com:443")}) {
    const grpc::Status s = FirstStatus(addresses[0], forged, &status);
    EXPECT_EQ(s.error_code(), grpc::NOT_FOUND) << s.error_message();
  }
}

// Forwarded calls carry the caller's token, and the owner decides who may
// see the job: its submitter through any replica, another identity nowhere.
TEST(ReplicaTest, ForwardedCallsActAsTheCaller) {
  TempDir dir;
  {
    std::ofstream tokens(dir / "tokens");
    tokens << "alice:alice-token\nbob:bob-token\n";
  }
  {
    std::ofstream(dir / "alice") << "alice-token\n";
    std::ofstream(dir / "bob") << "bob-token\n";
  }
  std::vector<std::unique_ptr<ServerProcess>> replicas;
  for (int i = 0; i < 2; ++i) {
    fs::create_directories(dir / absl::StrCat("r", i));
    replicas.push_back(Replica(dir / absl::StrCat("r", i),
                               {"--auth-token-file", dir / "tokens"}));
    ASSERT_TRUE(replicas.back()->Start());
  }
  const std::string a = replicas[0]->address();
  const std::string b = replicas[1]->address();
  CommandResult submit =
      Cli(Cat(Cat({"submit"}, kSmallJob),
              {"--server", a, "--token-file", dir / "alice"}));
  ASSERT_EQ(submit.exit_code, 0) << submit.err;
  const std::string id = Trim(submit.out);
  CommandResult alice = Cli(
      {"watch", id, "--quiet", "--server", b, "--token-file", dir / "alice"});
  EXPECT_EQ(alice.exit_code, 0) << alice.err;
  CommandResult bob =
      Cli({"watch", id, "--quiet", "--server", b, "--token-file", dir / "bob"});
  EXPECT_EQ(bob.exit_code, 1);
  EXPECT_THAT(bob.err, HasSubstr("no such job"));
  CommandResult nobody = Cli({"watch", id, "--quiet", "--server", b});
  EXPECT_EQ(nobody.exit_code, 1);
  EXPECT_THAT(nobody.err, HasSubstr("refused the credentials"));
}

// With TLS, a replica verifies the owner with --peer-tls-ca.
TEST(ReplicaTest, ForwardingOverTls) {
  TempDir dir;
  const std::string script = absl::StrCat(
      "set -e; cd ", dir / "", "; exec >openssl.log 2>&1\n",
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=test-ca "
      "-keyout ca.key -out ca.pem\n",
      "openssl req -newkey rsa:2048 -nodes -subj /CN=replica "
      "-keyout server.key -out server.csr\n",
      "printf 'subjectAltName=IP:127.0.0.1\\n' > san.ext\n",
      "openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key "
      "-CAcreateserial -days 2 -extfile san.ext -out server.pem\n");
  ASSERT_EQ(RunCommand({"/bin/sh", "-c", script}).exit_code, 0)
      << ReadFileOrEmpty(dir / "openssl.log");
  const std::vector<std::string> tls = {"--tls-cert", dir / "server.pem",
                                        "--tls-key", dir / "server.key"};
  std::vector<std::unique_ptr<ServerProcess>> replicas;
  for (int i = 0; i < 2; ++i) {
    fs::create_directories(dir / absl::StrCat("r", i));
    std::vector<std::string> extra = tls;
    // Replica 1 trusts no CA for its peers but the system's: forwarding
    // from it must fail verification.
    if (i == 0) extra = Cat(extra, {"--peer-tls-ca", dir / "ca.pem"});
    replicas.push_back(
        Replica(dir / absl::StrCat("r", i), extra, dir / "ca.pem"));
    ASSERT_TRUE(replicas.back()->Start());
  }
  const std::vector<std::string> ca = {"--tls-ca", dir / "ca.pem"};
  CommandResult submit =
      Cli(Cat(Cat({"submit"}, kSmallJob),
              Cat(ca, {"--server", replicas[1]->address()})));
  ASSERT_EQ(submit.exit_code, 0) << submit.err;
  const std::string id = Trim(submit.out);
  CommandResult through_0 = Cli(
      Cat({"watch", id, "--quiet", "--server", replicas[0]->address()}, ca));
  EXPECT_EQ(through_0.exit_code, 0) << through_0.err << replicas[0]->Log();
  // The other way, the owner's certificate is not trusted.
  CommandResult submit0 =
      Cli(Cat(Cat({"submit"}, kSmallJob),
              Cat(ca, {"--server", replicas[0]->address()})));
  ASSERT_EQ(submit0.exit_code, 0) << submit0.err;
  v1::JobStatus status;
  auto channel = grpc::CreateChannel(
      replicas[1]->address(),
      grpc::SslCredentials({ReadFileOrEmpty(dir / "ca.pem"), "", ""}));
  auto stub = v1::InterSlice::NewStub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(30));
  v1::WatchRequest request;
  request.set_job_id(Trim(submit0.out));
  auto reader = stub->Watch(&context, request);
  while (reader->Read(&status)) {
  }
  const grpc::Status s = reader->Finish();
  EXPECT_EQ(s.error_code(), grpc::UNAVAILABLE) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr(replicas[0]->address()));
}

}  // namespace
}  // namespace interslice::testing
