// Test helpers shared by the DICOM output tests: dciodvfy (dicom3tools) as
// the validator, and small DCMTK accessors.
#ifndef INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_
#define INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_

#include <cstdio>
#include <filesystem>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"

namespace interslice::testing {

inline constexpr char kDciodvfy[] = "/usr/bin/dciodvfy";

// dciodvfy's output lines for `path` (it writes to stderr).
inline std::vector<std::string> Dciodvfy(const std::string& path) {
  std::vector<std::string> lines;
  const std::string command = std::string(kDciodvfy) + " '" + path + "' 2>&1";
  FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) return {"Error - cannot run dciodvfy"};
  char buffer[4096];
  while (std::fgets(buffer, sizeof(buffer), pipe) != nullptr) {
    std::string line(buffer);
    while (!line.empty() && (line.back() == '\n' || line.back() == '\r')) {
      line.pop_back();
    }
    lines.push_back(line);
  }
  ::pclose(pipe);
  return lines;
}

// The number of dciodvfy "Error" lines over `paths` (each one printed).
inline int DciodvfyErrors(const std::vector<std::string>& paths) {
  int errors = 0;
  for (const std::string& path : paths) {
    for (const std::string& line : Dciodvfy(path)) {
      if (line.find("Error") == std::string::npos) continue;
      ++errors;
      std::printf("dciodvfy %s: %s\n",
                  std::filesystem::path(path).filename().c_str(), line.c_str());
    }
  }
  return errors;
}

// Runs dciodvfy on every file; fails on any "Error" line, prints each
// distinct warning once.
inline void ExpectValidIod(const std::vector<std::string>& paths) {
  ASSERT_TRUE(std::filesystem::exists(kDciodvfy))
      << "dciodvfy (dicom3tools) missing; run scripts/install-deps.sh";
  std::set<std::string> warnings;
  for (const std::string& path : paths) {
    for (const std::string& line : Dciodvfy(path)) {
      EXPECT_THAT(line, ::testing::Not(::testing::HasSubstr("Error")))
          << std::filesystem::path(path).filename();
      if (line.find("Warning") != std::string::npos) warnings.insert(line);
    }
  }
  for (const std::string& w : warnings) {
    std::printf(
        "dciodvfy %s: %s\n",
        paths.empty() ? "" : std::filesystem::path(paths[0]).filename().c_str(),
        w.c_str());
  }
}

inline std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  return std::string(value.c_str());
}

inline std::unique_ptr<DcmFileFormat> LoadDicom(const std::string& path) {
  auto file = std::make_unique<DcmFileFormat>();
  EXPECT_TRUE(file->loadFile(OFFilename(path.c_str())).good()) << path;
  return file;
}

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_
