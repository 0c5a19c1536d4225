#include "core/common/sha256.h"

#include <openssl/evp.h>

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <fstream>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"

namespace interslice {

struct Sha256::State {
  EVP_MD_CTX* ctx = nullptr;
};

Sha256::Sha256() : state_(std::make_unique<State>()) {
  state_->ctx = EVP_MD_CTX_new();
  EVP_DigestInit_ex(state_->ctx, EVP_sha256(), nullptr);
}

Sha256::~Sha256() { EVP_MD_CTX_free(state_->ctx); }

void Sha256::Update(std::string_view data) {
  EVP_DigestUpdate(state_->ctx, data.data(), data.size());
}

std::string Sha256::Finish() {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_DigestFinal_ex(state_->ctx, digest, &length);
  return std::string(reinterpret_cast<const char*>(digest), length);
}

absl::StatusOr<std::string> Sha256OfFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError("cannot open a file to hash it");
  Sha256 hash;
  std::vector<char> buffer(1 << 16);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    hash.Update(std::string_view(buffer.data(), in.gcount()));
  }
  if (in.bad()) return absl::DataLossError("read error while hashing a file");
  return hash.Finish();
}

std::vector<absl::StatusOr<std::string>> Sha256OfFiles(
    const std::vector<std::string>& paths, int threads) {
  std::vector<absl::StatusOr<std::string>> shas(
      paths.size(), absl::InternalError("not hashed"));
  std::vector<std::pair<int64_t, size_t>> by_size;  // (-size, index)
  for (size_t n = 0; n < paths.size(); ++n) {
    std::error_code ec;
    const auto size = std::filesystem::file_size(paths[n], ec);
    by_size.push_back({ec ? 0 : -static_cast<int64_t>(size), n});
  }
  std::sort(by_size.begin(), by_size.end());
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t k = next++; k < by_size.size(); k = next++) {
      const size_t n = by_size[k].second;
      shas[n] = Sha256OfFile(paths[n]);
    }
  };
  const int extra =
      std::min<int>(std::max(threads, 1), static_cast<int>(paths.size())) - 1;
  std::vector<std::thread> pool;
  for (int t = 0; t < extra; ++t) pool.emplace_back(work);
  work();
  for (std::thread& t : pool) t.join();
  return shas;
}

std::string HexString(std::string_view bytes) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string out;
  out.reserve(bytes.size() * 2);
  for (unsigned char c : bytes) {
    out.push_back(kDigits[c >> 4]);
    out.push_back(kDigits[c & 15]);
  }
  return out;
}

}  // namespace interslice
