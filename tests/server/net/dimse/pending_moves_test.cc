#include "server/net/dimse/pending_moves.h"

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/temp_dir.h"

namespace interslice::server::dimse {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

class PendingMovesTest : public ::testing::Test {
 protected:
  void SetUp() override { fs::create_directories(dest_); }
  // A received file (the registry trusts the listener's scan; any bytes).
  std::string Staged(int bytes) {
    const std::string path =
        (dir_.path() / ("staged-" + std::to_string(++n_))).string();
    std::ofstream(path) << std::string(bytes, 'x');
    return path;
  }
  int Files() {
    int n = 0;
    for (const auto& f : fs::directory_iterator(dest_))
      n += f.is_regular_file();
    return n;
  }

  testing::TempDir dir_{"interslice_pending_moves_"};
  fs::path dest_ = dir_.path() / "job";
  int n_ = 0;
};

// Two jobs pulling the same series from the same peer: the second's move
// waits for the first to end instead of failing at once, and gives up with
// its own status (cancelled) when told to.
TEST_F(PendingMovesTest, SecondMoveOfTheSameSeriesWaitsForTheFirst) {
  PendingMoves moves;
  auto first =
      moves.Register("ORTHANC", "1.2", "1.2.3", dest_.string(), 10, 1000);
  ASSERT_TRUE(first.ok()) << first.status();
  std::atomic<bool> closed{false};
  std::atomic<int> polls{0};
  absl::StatusOr<std::shared_ptr<PendingMoves::Move>> second =
      absl::UnknownError("not registered");
  std::thread waiter([&] {
    second = moves.Register("ORTHANC", "1.2", "1.2.3", dest_.string(), 10, 1000,
                            [&] {
                              ++polls;
                              return absl::OkStatus();
                            });
    // Only after the first move closed.
    EXPECT_TRUE(closed.load());
  });
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (polls.load() < 2 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_GE(polls.load(), 2);  // still waiting after a poll period
  // A move of another series from the same peer is not held up meanwhile.
  EXPECT_TRUE(
      moves.Register("ORTHANC", "1.2", "1.2.4", dest_.string(), 10, 1000).ok());
  closed = true;
  moves.Close(*first);
  waiter.join();
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_NE(*second, *first);
  EXPECT_EQ(moves.Find("ORTHANC", "1.2", "1.2.3"), *second);

  // A third one while the second is open, whose job is cancelled.
  auto third = moves.Register("ORTHANC", "1.2", "1.2.3", dest_.string(), 10,
                              1000, [] { return absl::CancelledError("job"); });
  EXPECT_EQ(third.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(moves.Find("ORTHANC", "1.2", "1.2.3"), *second);
}

TEST_F(PendingMovesTest, KeepsInstancesOfItsSeriesFromItsPeerOnly) {
  PendingMoves moves;
  auto move = moves.Register(" ORTHANC ", "1.2", "1.2.3", dest_.string(),
                             /*max_instances=*/10, /*max_bytes=*/1000);
  ASSERT_TRUE(move.ok()) << move.status();
  EXPECT_TRUE(moves.Expects("ORTHANC"));
  EXPECT_FALSE(moves.Expects("OTHER"));
  EXPECT_EQ(moves.Find("ORTHANC", "1.2", "1.2.3"), *move);
  EXPECT_EQ(moves.Find("ORTHANC", "1.2", "1.2.4"), nullptr);
  EXPECT_EQ(moves.Find("OTHER", "1.2", "1.2.3"), nullptr);
  const std::string staged = Staged(100);
  ASSERT_TRUE((*move)->Accept(7, staged, 100).ok());
  EXPECT_FALSE(fs::exists(staged));
  EXPECT_TRUE(fs::exists(dest_ / "pacs-000001.dcm"));
  EXPECT_EQ((*move)->instances(), 1);
  EXPECT_EQ((*move)->bytes(), 100);
  // A second move of the same series from the same peer waits its turn.
  auto again =
      moves.Register("ORTHANC", "1.2", "1.2.3", dest_.string(), 10, 1000);
  EXPECT_EQ(again.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST_F(PendingMovesTest, LimitsFailTheMoveAndLaterInstancesToo) {
  PendingMoves moves;
  auto move = moves.Register("PACS", "1", "2", dest_.string(), 2, 250);
  ASSERT_TRUE(move.ok());
  ASSERT_TRUE((*move)->Accept(1, Staged(100), 100).ok());
  const std::string big = Staged(200);
  const absl::Status over = (*move)->Accept(1, big, 200);
  EXPECT_EQ(over.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(over.message(), HasSubstr("larger than 250 bytes"));
  EXPECT_FALSE(fs::exists(big));
  EXPECT_EQ((*move)->error().code(), absl::StatusCode::kResourceExhausted);
  // The series cannot arrive whole any more: a small one is refused too.
  EXPECT_FALSE((*move)->Accept(1, Staged(10), 10).ok());
  EXPECT_EQ(Files(), 1);
  (*move)->RemoveKept();
  EXPECT_EQ(Files(), 0);

  auto count = moves.Register("PACS", "1", "3", dest_.string(), 1, 1000);
  ASSERT_TRUE(count.ok());
  ASSERT_TRUE((*count)->Accept(1, Staged(1), 1).ok());
  EXPECT_THAT((*count)->Accept(1, Staged(1), 1).message(),
              HasSubstr("more than 1 instances"));
}

TEST_F(PendingMovesTest,
       ClosedMoveRefusesLateInstancesAndCanBeRegisteredAgain) {
  PendingMoves moves;
  auto move = moves.Register("PACS", "1", "2", dest_.string(), 10, 1000);
  ASSERT_TRUE(move.ok());
  moves.Close(*move);
  // Still found (so the listener never hands a late instance to the rules),
  // but refused.
  ASSERT_EQ(moves.Find("PACS", "1", "2"), *move);
  const std::string late = Staged(10);
  EXPECT_EQ((*move)->Accept(1, late, 10).code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_FALSE(fs::exists(late));
  EXPECT_EQ(Files(), 0);
  auto next = moves.Register("PACS", "1", "2", dest_.string(), 10, 1000);
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_EQ(moves.Find("PACS", "1", "2"), *next);
}

TEST_F(PendingMovesTest, SettledOnlyWhenCountArrivedAndAssociationsEnded) {
  PendingMoves moves;
  auto move = moves.Register("PACS", "1", "2", dest_.string(), 10, 1000);
  ASSERT_TRUE(move.ok());
  const auto soon = [] {
    return std::chrono::steady_clock::now() + std::chrono::milliseconds(50);
  };
  EXPECT_FALSE((*move)->WaitSettled(1, soon()));  // nothing arrived
  ASSERT_TRUE((*move)->Accept(5, Staged(1), 1).ok());
  EXPECT_FALSE((*move)->WaitSettled(1, soon()));  // association 5 still open
  std::thread ender([&] { (*move)->AssociationEnded(5); });
  EXPECT_TRUE((*move)->WaitSettled(
      1, std::chrono::steady_clock::now() + std::chrono::seconds(600)));
  ender.join();
  EXPECT_FALSE((*move)->WaitSettled(2, soon()));  // one short
}

}  // namespace
}  // namespace interslice::server::dimse
