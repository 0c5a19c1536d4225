// Test helper: a fresh folder per test, removed afterwards.
#ifndef INTERSLICE_TESTS_TESTING_TEMP_DIR_H_
#define INTERSLICE_TESTS_TESTING_TEMP_DIR_H_

#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <string>
#include <system_error>

#include "gtest/gtest.h"

namespace interslice::testing {

class TempDir {
 public:
  // Named "<prefix><test name>_<pid>_<counter>" under the system temp folder.
  explicit TempDir(const std::string& prefix = "interslice_") {
    static std::atomic<int> counter{0};
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path_ = std::filesystem::temp_directory_path() /
            (prefix + (info != nullptr ? info->name() : "test") + "_" +
             std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::filesystem::remove_all(path_);
    std::filesystem::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  const std::filesystem::path& path() const { return path_; }
  std::string str() const { return path_.string(); }
  // The path of `name` inside the folder, as a string (for argument lists).
  std::string operator/(const std::string& name) const {
    return (path_ / name).string();
  }

 private:
  std::filesystem::path path_;
};

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_TEMP_DIR_H_
