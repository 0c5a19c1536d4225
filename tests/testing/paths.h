// Where a test finds the source tree and the binaries under test.
//
// These are values at run time, from one small file that CMake generates in
// the build folder (tests/testing/CMakeLists.txt), and not compile
// definitions: a definition holding the checkout's absolute path would make
// every test object depend on where the checkout is, so ccache could not
// share test objects between two clones (a new CI clone compiled every test
// again, although the sources were the same).
#ifndef INTERSLICE_TESTS_TESTING_PATHS_H_
#define INTERSLICE_TESTS_TESTING_PATHS_H_

#include <string>

namespace interslice::testing {

// The repository root, absolute, without a trailing slash.
const char* SourceDir();
// tests/data under the repository root.
const char* TestDataDir();
// The `interslice` client binary of this build folder.
const char* CliPath();
// The `interslice-server` binary of this build folder; empty in a build
// without the server (INTERSLICE_BUILD_SERVER=OFF).
const char* ServerPath();
// tests/server/app/slow_proxy.py: a TCP proxy that delays the first bytes.
std::string SlowProxyPath();

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_PATHS_H_
