#include "core/common/compute.h"

#include <chrono>

#include "gtest/gtest.h"

namespace interslice {
namespace {

TEST(CancellationTokenTest, StartsOkAndCancels) {
  CancellationToken token;
  EXPECT_TRUE(token.Check().ok());
  token.Cancel();
  EXPECT_EQ(token.Check().code(), absl::StatusCode::kCancelled);
  EXPECT_TRUE(token.IsCancelled());
}

TEST(CancellationTokenTest, DeadlineInThePastExpires) {
  CancellationToken token;
  token.SetDeadline(std::chrono::steady_clock::now() - std::chrono::seconds(1));
  EXPECT_EQ(token.Check().code(), absl::StatusCode::kDeadlineExceeded);
}

TEST(CancellationTokenTest, DeadlineInTheFutureDoesNotExpire) {
  CancellationToken token;
  token.SetDeadline(std::chrono::steady_clock::now() + std::chrono::hours(1));
  EXPECT_TRUE(token.Check().ok());
}

TEST(ComputeContextTest, NullTokenNeverCancels) {
  ComputeContext context;
  EXPECT_TRUE(context.CheckCancelled().ok());
  CancellationToken token;
  token.Cancel();
  context.cancel = &token;
  EXPECT_FALSE(context.CheckCancelled().ok());
}

}  // namespace
}  // namespace interslice
