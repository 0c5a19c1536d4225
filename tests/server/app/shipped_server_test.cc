// The server binary a build ships carries the job worker's crash hook
// (server/engine/job_worker.h, INTERSLICE_WORKER_FAULT) only when the build
// asked for it (CMake option INTERSLICE_FAULT_INJECTION: the instrumented test
// build). The hook reads an environment variable by name, so the name is in
// the binary exactly when the hook is compiled in.
#include <fstream>
#include <iterator>
#include <string>

#include "gtest/gtest.h"
#include "tests/testing/paths.h"

namespace interslice {
namespace {

int CountOccurrences(const std::string& haystack, const std::string& needle) {
  int count = 0;
  for (size_t at = haystack.find(needle); at != std::string::npos;
       at = haystack.find(needle, at + needle.size())) {
    ++count;
  }
  return count;
}

TEST(ShippedServerTest, HasTheFaultInjectionHookOnlyInTestBuilds) {
  const std::string path = testing::ServerPath();
  ASSERT_FALSE(path.empty()) << "this build has no server";
  std::ifstream in(path, std::ios::binary);
  ASSERT_TRUE(in) << "cannot read " << path;
  const std::string binary((std::istreambuf_iterator<char>(in)),
                           std::istreambuf_iterator<char>());
  ASSERT_GT(binary.size(), 1000u) << path;
  const int found = CountOccurrences(binary, "INTERSLICE_WORKER_FAULT");
#ifdef INTERSLICE_FAULT_INJECTION
  EXPECT_GE(found, 1) << "the fault-injection build's server lacks its hook";
#else
  EXPECT_EQ(found, 0)
      << path
      << " reads INTERSLICE_WORKER_FAULT: a shipped server must "
         "not carry the crash hook";
#endif
}

}  // namespace
}  // namespace interslice
