#include "core/surface/atomic_file.h"

#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace interslice::surface_internal {
namespace {

std::string RandomSuffix() {
  thread_local std::mt19937_64 engine{std::random_device{}()};
  return absl::StrFormat("%016x", engine());
}

absl::Status IoError(const std::string& what, const std::string& path,
                     int error) {
  return absl::InternalError(
      absl::StrCat("cannot ", what, " ", path, ": ", std::strerror(error)));
}

}  // namespace

void ChunkedWriter::Flush() {
  if (!buffer_.empty() && error_ == 0 &&
      std::fwrite(buffer_.data(), 1, buffer_.size(), file_) != buffer_.size()) {
    error_ = errno != 0 ? errno : EIO;
  }
  buffer_.clear();
}

absl::Status WriteFileAtomically(
    const std::string& path, const std::function<void(ChunkedWriter&)>& fill) {
  const std::string temp = absl::StrCat(path, ".tmp-", RandomSuffix());
  // "x": fail rather than reuse an existing file of that name.
  std::FILE* file = std::fopen(temp.c_str(), "wbx");
  if (file == nullptr) return IoError("create", path, errno);

  int error = 0;
  {
    ChunkedWriter writer(file);
    fill(writer);
    writer.Flush();
    error = writer.error();
  }
  if (error == 0 && std::fflush(file) != 0) error = errno;
  if (error == 0 && ::fsync(fileno(file)) != 0) error = errno;
  if (std::fclose(file) != 0 && error == 0) error = errno;
  if (error != 0) {
    std::remove(temp.c_str());
    return IoError("write", path, error);
  }
  std::error_code ec;
  std::filesystem::rename(temp, path, ec);
  if (ec) {
    std::remove(temp.c_str());
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", ec.message()));
  }
  return absl::OkStatus();
}

}  // namespace interslice::surface_internal
