// External programs the tests need (dciodvfy, gzip, python3, Orthanc, ...),
// found at run time on PATH so that a run with a tool missing shows what
// happens. Policy (tests must not pass without testing):
//  - a gtest that needs a tool FAILS when it is missing, naming the tool,
//    everywhere (scripts/install-deps.sh, which scripts/test.sh runs first,
//    installs every one of them);
//  - the script-level checks that need a heavier set-up (node for the viewer
//    test, yamllint, a container runtime for scripts/test-deploy.sh) fail in
//    CI (CI=true) and are reported SKIPPED elsewhere (tests/testing/
//    require-tool.sh, ctest's "Skipped"), never passed.
#ifndef INTERSLICE_TESTS_TESTING_TOOLS_H_
#define INTERSLICE_TESTS_TESTING_TOOLS_H_

#include <string>
#include <vector>

namespace interslice::testing {

// Whether this run is CI's: the environment variable CI is "true".
bool InCi();

// The first executable file called `name` in the directories of PATH, then
// in `extra_dirs` (for programs outside a user's PATH, e.g. /usr/sbin); ""
// when there is none.
std::string FindTool(const std::string& name,
                     const std::vector<std::string>& extra_dirs = {});

// FindTool, and when the tool is missing a failure of the current test
// naming it (ADD_FAILURE: the caller returns, e.g.
//   const std::string gzip = RequireTool("gzip");
//   ASSERT_FALSE(gzip.empty());
std::string RequireTool(const std::string& name,
                        const std::vector<std::string>& extra_dirs = {});

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_TOOLS_H_
