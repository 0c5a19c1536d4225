// UID generation: "2.25." + UUID (ITU-T X.667 section 6.3, DICOM PS3.5 B.2)
// or a caller's root followed by digits; random (UUID version 4) or derived
// from a name (UUID version 5, RFC 4122 section 4.3).
#include <cstdint>
#include <random>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "core/dicom_out/dicom_writer.h"
#include "openssl/evp.h"

namespace interslice {
namespace {

constexpr size_t kMaxUidLength = 64;
// Random digits after a caller's root: 24 decimal digits are ~80 bits, enough
// that collisions between independently generated UIDs are negligible.
constexpr size_t kMinRandomDigits = 24;

// 128 random bits. std::random_device reads the OS entropy source on Linux,
// so UIDs from different processes or machines do not collide the way a
// time-seeded generator's would.
unsigned __int128 Random128() {
  thread_local std::random_device device;
  unsigned __int128 value = 0;
  for (int i = 0; i < 4; ++i) value = (value << 32) | device();
  return value;
}

std::string ToDecimal(unsigned __int128 value) {
  if (value == 0) return "0";
  std::string digits;
  while (value != 0) {
    digits.push_back(static_cast<char>('0' + static_cast<int>(value % 10)));
    value /= 10;
  }
  return std::string(digits.rbegin(), digits.rend());
}

absl::Status ValidateRoot(const std::string& root) {
  if (root.size() + 1 + kMinRandomDigits > kMaxUidLength) {
    return absl::InvalidArgumentError(absl::StrCat(
        "UID root is too long (", root.size(), " characters, at most ",
        kMaxUidLength - 1 - kMinRandomDigits, ")"));
  }
  size_t component_start = 0;
  for (size_t i = 0; i <= root.size(); ++i) {
    if (i == root.size() || root[i] == '.') {
      const size_t length = i - component_start;
      if (length == 0) {
        return absl::InvalidArgumentError(
            "UID root has an empty component (or a leading or trailing dot)");
      }
      if (length > 1 && root[component_start] == '0') {
        return absl::InvalidArgumentError(
            "UID root has a component with a leading zero");
      }
      component_start = i + 1;
    } else if (root[i] < '0' || root[i] > '9') {
      return absl::InvalidArgumentError(
          "UID root may contain only digits and dots");
    }
  }
  return absl::OkStatus();
}

// Sets the version nibble (bits 76..79 of the 128-bit value) and the RFC 4122
// variant (10 in bits 62..63).
unsigned __int128 MarkUuid(unsigned __int128 uuid, unsigned version) {
  const unsigned __int128 one = 1;
  uuid &= ~(static_cast<unsigned __int128>(0xF) << 76);
  uuid |= static_cast<unsigned __int128>(version & 0xF) << 76;
  uuid &= ~(static_cast<unsigned __int128>(0x3) << 62);
  uuid |= one << 63;
  return uuid;
}

// interslice's namespace for name-based UUIDs (RFC 4122 section 4.3): a
// fixed random UUID, 3f1c9a52-7d0e-4b6a-9c41-52e8d7a0b613. Never change it:
// every derived UID depends on it.
constexpr unsigned char kNamespace[16] = {0x3f, 0x1c, 0x9a, 0x52, 0x7d, 0x0e,
                                          0x4b, 0x6a, 0x9c, 0x41, 0x52, 0xe8,
                                          0xd7, 0xa0, 0xb6, 0x13};

// Root followed by the decimal digits of `value`, cut to fit 64 characters.
std::string UnderRoot(const std::string& root, unsigned __int128 value) {
  const size_t room = kMaxUidLength - root.size() - 1;
  std::string digits = ToDecimal(value);
  // Never a leading zero (ToDecimal gives none) and never longer than fits.
  if (digits.size() > room) digits.resize(room);
  return absl::StrCat(root, ".", digits);
}

}  // namespace

absl::StatusOr<std::string> DeriveDicomUid(const std::string& root,
                                           std::string_view name) {
  if (!root.empty()) {
    if (absl::Status status = ValidateRoot(root); !status.ok()) return status;
  }
  // UUID version 5: SHA-1 over the namespace's 16 bytes and the name; the
  // first 16 bytes of the digest, big-endian, with version and variant set.
  std::string message(reinterpret_cast<const char*>(kNamespace),
                      sizeof(kNamespace));
  message.append(name);
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int digest_length = 0;
  if (EVP_Digest(message.data(), message.size(), digest, &digest_length,
                 EVP_sha1(), nullptr) != 1 ||
      digest_length < 16) {
    return absl::InternalError("SHA-1 is not available for derived UIDs");
  }
  unsigned __int128 uuid = 0;
  for (int i = 0; i < 16; ++i) uuid = (uuid << 8) | digest[i];
  uuid = MarkUuid(uuid, 5);
  if (root.empty()) return absl::StrCat("2.25.", ToDecimal(uuid));
  return UnderRoot(root, uuid);
}

absl::StatusOr<std::string> GenerateDicomUid(const std::string& root) {
  if (root.empty()) {
    // A version 4 (random) UUID (RFC 4122 section 4.4).
    return absl::StrCat("2.25.", ToDecimal(MarkUuid(Random128(), 4)));
  }
  if (absl::Status status = ValidateRoot(root); !status.ok()) return status;
  return UnderRoot(root, Random128());
}

}  // namespace interslice
