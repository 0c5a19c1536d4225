// SHA-256 (OpenSSL's EVP interface): what the client and the server check
// uploaded files and artifacts with, and what names received instances.
#ifndef INTERSLICE_CORE_COMMON_SHA256_H_
#define INTERSLICE_CORE_COMMON_SHA256_H_

#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace interslice {

class Sha256 {
 public:
  Sha256();
  ~Sha256();
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;
  void Update(std::string_view data);
  // The 32-byte digest; the object must not be used afterwards.
  std::string Finish();

 private:
  struct State;
  std::unique_ptr<State> state_;
};

// SHA-256 of a whole file (32 raw bytes).
absl::StatusOr<std::string> Sha256OfFile(const std::string& path);

// SHA-256 of each file (32 raw bytes or the error of Sha256OfFile), in the
// order of `paths`, hashed on up to `threads` threads (< 1: one), largest
// files first so that one big file does not start last.
std::vector<absl::StatusOr<std::string>> Sha256OfFiles(
    const std::vector<std::string>& paths, int threads);

std::string HexString(std::string_view bytes);

}  // namespace interslice

#endif  // INTERSLICE_CORE_COMMON_SHA256_H_
