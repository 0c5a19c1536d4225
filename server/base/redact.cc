#include "server/base/redact.h"

#include <cctype>
#include <cerrno>
#include <cstring>

#include "absl/strings/match.h"
#include "server/base/log_safe.h"

namespace interslice::server {

std::string RedactPhi(absl::string_view message) {
  std::string out;
  out.reserve(message.size());
  size_t i = 0;
  while (i < message.size()) {
    if (std::isdigit(static_cast<unsigned char>(message[i])) &&
        (i == 0 || !std::isalnum(static_cast<unsigned char>(message[i - 1])))) {
      // Scan a run of digits and dots.
      size_t j = i;
      int dots = 0;
      while (j < message.size() &&
             (std::isdigit(static_cast<unsigned char>(message[j])) ||
              message[j] == '.')) {
        if (message[j] == '.') ++dots;
        ++j;
      }
      // A trailing '.' ends a sentence, not the UID.
      size_t end = j;
      if (end > i && message[end - 1] == '.') {
        --end;
        --dots;
      }
      if (dots >= 3) {
        out += "<uid>";
        i = end;
        continue;
      }
      out.append(message.data() + i, end - i);
      i = end;
      continue;
    }
    out.push_back(message[i]);
    ++i;
  }
  return LogSafe(out);
}

absl::Status DiskFullAsResourceExhausted(const absl::Status& status,
                                         bool disk_full) {
  if (status.ok() || status.code() == absl::StatusCode::kCancelled ||
      status.code() == absl::StatusCode::kResourceExhausted) {
    return status;
  }
  const bool says_so =
      absl::StrContains(status.message(), std::strerror(ENOSPC)) ||
      absl::StrContains(status.message(), std::strerror(EDQUOT));
  const bool unexplained = status.code() == absl::StatusCode::kInternal ||
                           status.code() == absl::StatusCode::kUnknown;
  if (says_so || (disk_full && unexplained)) {
    return absl::ResourceExhaustedError(
        "disk full: the server has no room left for this job's files; "
        "retry when space is free");
  }
  return status;
}

}  // namespace interslice::server
