#include "tests/testing/files.h"

#include <filesystem>

#include "gtest/gtest.h"
#include "tests/testing/process.h"

namespace interslice::testing {
namespace fs = std::filesystem;

void ExpectSameFiles(const std::string& expected_dir,
                     const std::string& actual_dir, int min_files,
                     const std::set<std::string>& except,
                     DicomComparison dicom) {
  int files = 0;
  for (const auto& entry : fs::recursive_directory_iterator(expected_dir)) {
    if (!entry.is_regular_file()) continue;
    const std::string name =
        fs::relative(entry.path(), expected_dir).generic_string();
    if (except.count(name) > 0) continue;
    ++files;
    const std::string actual = (fs::path(actual_dir) / name).string();
    if (!fs::exists(actual)) {
      ADD_FAILURE() << actual << " is missing";
      continue;
    }
    if (dicom == DicomComparison::kSameSize &&
        entry.path().extension() == ".dcm") {
      EXPECT_EQ(fs::file_size(entry.path()), fs::file_size(actual))
          << actual << " differs in size from " << entry.path().string();
      continue;
    }
    EXPECT_TRUE(ReadFileOrEmpty(entry.path().string()) ==
                ReadFileOrEmpty(actual))
        << actual << " differs from " << entry.path().string();
  }
  EXPECT_GE(files, min_files) << "files compared in " << expected_dir;
}

}  // namespace interslice::testing
