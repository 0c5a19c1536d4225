// UID generation: "2.25." + UUID (ITU-T X.667 section 6.3, DICOM PS3.5 B.2)
// or a caller's root followed by random digits.
#include <cstdint>
#include <random>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "core/dicom_out/dicom_writer.h"

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

}  // namespace

absl::StatusOr<std::string> GenerateDicomUid(const std::string& root) {
  if (root.empty()) {
    unsigned __int128 uuid = Random128();
    // A version 4 (random) UUID: version nibble 0100 in bits 76..79, variant
    // 10 in bits 62..63 (RFC 4122 section 4.4).
    const unsigned __int128 one = 1;
    uuid &= ~(static_cast<unsigned __int128>(0xF) << 76);
    uuid |= static_cast<unsigned __int128>(0x4) << 76;
    uuid &= ~(static_cast<unsigned __int128>(0x3) << 62);
    uuid |= one << 63;
    return absl::StrCat("2.25.", ToDecimal(uuid));
  }
  if (absl::Status status = ValidateRoot(root); !status.ok()) return status;
  const size_t room = kMaxUidLength - root.size() - 1;
  std::string digits = ToDecimal(Random128());
  // Never a leading zero (ToDecimal gives none) and never longer than fits.
  if (digits.size() > room) digits.resize(room);
  return absl::StrCat(root, ".", digits);
}

}  // namespace interslice
