#include "tests/testing/dciodvfy.h"

#include <cstdio>
#include <filesystem>
#include <set>
#include <sstream>

#include "gtest/gtest.h"
#include "tests/testing/process.h"
#include "tests/testing/tools.h"

namespace interslice::testing {

DciodvfyReport Dciodvfy(const std::string& path) {
  DciodvfyReport report;
  const std::string dciodvfy = RequireTool("dciodvfy");
  if (dciodvfy.empty()) {
    report.errors.push_back("Error - dciodvfy is not installed");
    return report;
  }
  // dciodvfy writes its findings to stderr.
  const CommandResult r = RunCommand({dciodvfy, path}, 300);
  report.exit_code = r.exit_code;
  std::istringstream lines(r.out + r.err);
  for (std::string line; std::getline(lines, line);) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.find("Error") != std::string::npos ||
        line.find("Abort") != std::string::npos) {
      report.errors.push_back(line);
    } else if (line.find("Warning") != std::string::npos) {
      report.warnings.push_back(line);
    }
  }
  if (r.timed_out) report.errors.push_back("Error - dciodvfy timed out");
  return report;
}

int DciodvfyErrors(const std::vector<std::string>& paths,
                   std::string* details) {
  int count = 0;
  for (const std::string& path : paths) {
    const std::string name = std::filesystem::path(path).filename().string();
    DciodvfyReport report = Dciodvfy(path);
    if (report.exit_code != 0 && report.errors.empty()) {
      report.errors.push_back("Error - dciodvfy exited with status " +
                              std::to_string(report.exit_code));
    }
    for (const std::string& line : report.errors) {
      ++count;
      std::printf("dciodvfy %s: %s\n", name.c_str(), line.c_str());
      if (details != nullptr) *details += name + ": " + line + "\n";
    }
  }
  return count;
}

void ExpectValidIod(const std::vector<std::string>& paths) {
  std::set<std::string> warnings;
  for (const std::string& path : paths) {
    const std::string name = std::filesystem::path(path).filename().string();
    const DciodvfyReport report = Dciodvfy(path);
    EXPECT_EQ(report.exit_code, 0) << "dciodvfy " << name;
    for (const std::string& line : report.errors) {
      ADD_FAILURE() << "dciodvfy " << name << ": " << line;
    }
    warnings.insert(report.warnings.begin(), report.warnings.end());
  }
  for (const std::string& w : warnings) {
    std::printf(
        "dciodvfy %s: %s\n",
        paths.empty() ? "" : std::filesystem::path(paths[0]).filename().c_str(),
        w.c_str());
  }
}

}  // namespace interslice::testing
