#include "tests/testing/process.h"

#include <set>

#include "gtest/gtest.h"

namespace interslice::testing {
namespace {

// Regression: Orthanc::Start asks for its HTTP and DICOM ports one after the
// other, and CI saw both come back equal (Orthanc then refused to start).
// With bind(port 0) alone, 500 ports out of the ~14000 the kernel hands out
// for it repeat one another almost surely (about 9 repeats expected).
TEST(FreeTcpPortTest, NeverHandsOutTheSamePortTwice) {
  std::set<int> ports;
  for (int i = 0; i < 500; ++i) {
    const int port = FreeTcpPort();
    ASSERT_GT(port, 0) << "call " << i;
    EXPECT_TRUE(ports.insert(port).second)
        << "port " << port << " handed out again at call " << i;
  }
}

}  // namespace
}  // namespace interslice::testing
