#include "tests/testing/tools.h"

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <sstream>

#include "gtest/gtest.h"

namespace interslice::testing {

bool InCi() {
  const char* ci = std::getenv("CI");
  return ci != nullptr && std::string(ci) == "true";
}

std::string FindTool(const std::string& name,
                     const std::vector<std::string>& extra_dirs) {
  std::vector<std::string> dirs;
  if (const char* path = std::getenv("PATH")) {
    std::stringstream in(path);
    for (std::string dir; std::getline(in, dir, ':');) {
      if (!dir.empty()) dirs.push_back(dir);
    }
  }
  dirs.insert(dirs.end(), extra_dirs.begin(), extra_dirs.end());
  for (const std::string& dir : dirs) {
    const std::string candidate = (std::filesystem::path(dir) / name).string();
    std::error_code ec;
    if (std::filesystem::is_regular_file(candidate, ec) &&
        ::access(candidate.c_str(), X_OK) == 0) {
      return candidate;
    }
  }
  return "";
}

std::string RequireTool(const std::string& name,
                        const std::vector<std::string>& extra_dirs) {
  std::string path = FindTool(name, extra_dirs);
  if (path.empty()) {
    ADD_FAILURE() << name
                  << " is not installed (not on PATH): this test needs it; "
                     "scripts/install-deps.sh installs it";
  }
  return path;
}

}  // namespace interslice::testing
