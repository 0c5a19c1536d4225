// The `interslice` binary under test, run through the shell: for the CLI
// tests, whose cases are whole command lines: CliPath() (tests/testing/
// paths.h); the including target depends on `interslice`
// (tests/client/CMakeLists.txt).
#ifndef INTERSLICE_TESTS_TESTING_CLI_H_
#define INTERSLICE_TESTS_TESTING_CLI_H_

#include <string>

#include "tests/testing/paths.h"
#include "tests/testing/process.h"

namespace interslice::testing {

// `interslice <arguments>` (one command line, shell quoting applies), its
// stdout and stderr interleaved in `out`.
inline CommandResult RunCli(const std::string& arguments) {
  return RunShell(std::string(::interslice::testing::CliPath()) + " " +
                  arguments);
}

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_CLI_H_
